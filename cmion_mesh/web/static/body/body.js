// The body's page: renders the state the daemon pushes over the WebSocket, plays the companion's
// voice with lip movement, and sends what the page senses (visitor, yes/no, typed commands).
// No polling: everything arrives as it happens; nothing runs while nothing happens but CSS.
"use strict";

const $ = (id) => document.getElementById(id);
const body = document.body;
const voice = $("voice");
let socket = null;
let state = null;
let spoken = "";          // id of the utterance already started
let audioContext = null;  // created on the first user gesture or autoplay permission
let analyser = null;
let mouthFrame = 0;
let retry = 500;

const params = new URLSearchParams(location.search);
const layout = params.get("layout");

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const key = params.get("key");
  socket = new WebSocket(`${scheme}://${location.host}/ws` + (key ? `?key=${encodeURIComponent(key)}` : ""));
  socket.onopen = () => { body.dataset.connected = "true"; $("status").textContent = "connected"; retry = 500; };
  socket.onclose = () => {
    body.dataset.connected = "false";
    $("status").textContent = "reconnecting";
    setTimeout(connect, retry);  // the daemon restarted or the link broke: come back, a little slower each time
    retry = Math.min(retry * 2, 10000);
  };
  socket.onmessage = (message) => {
    const data = JSON.parse(message.data);
    if (data.type === "state") render(data);
    else if (data.type === "error") notice(data.error);
    else if (data.type === "ok") notice("");
    else if (data.type === "access") {
      body.dataset.act = data.act ? "true" : "false";
      if (!data.act) notice("watching only: the daemon's printed address (with its key) lets a visitor act here");
    }
  };
}

function send(message) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
  else notice("not connected to the body");
}

function notice(text) { $("notice").textContent = text; }

function render(next) {
  const before = state;
  state = next;
  const lay = layout || next.layout;
  body.className = `layout-${lay === "phone" || lay === "screen" ? lay : "auto"}`;
  $("embodiment").textContent = next.companion ? `${next.companion} on ${next.embodiment}` : `${next.embodiment} (empty)`;
  document.title = `${next.embodiment}: ${next.companion || "empty"}`;
  body.dataset.embodiment = next.embodiment || "";
  body.dataset.companion = next.companion || "";
  body.dataset.face = next.face;
  body.dataset.expression = next.expression;
  body.dataset.senses = next.senses.join(" ");
  showTransition(next);
  showGesture(next);

  const asking = next.asking;
  $("question").hidden = !asking;
  if (asking) $("question-text").textContent = `Waiting for ${asking}'s answer: yes or no?`;
  if (asking && !(before && before.asking)) $("yes").focus({ preventScroll: true });
  $("visitor-form").hidden = !next.senses.includes("visitor");
  $("command-form").hidden = !next.senses.includes("command");
  const here = new Set(next.visitors);
  const name = $("visitor-name").value.trim();
  $("visitor").setAttribute("aria-pressed", here.has(name) ? "true" : "false");
  $("visitor").textContent = here.has(name) ? "I am leaving" : "I am here";

  // The bubble holds the line being spoken, else the last one said here: it stays readable until
  // the next, and a page opened after it was spoken shows it too.
  const said = next.said;
  const speech = next.speech;
  const bubble = $("speech");
  const shown = speech ? speech.text : (next.companion && said.length ? said[said.length - 1] : "");
  if (bubble.textContent !== shown) bubble.textContent = shown;
  bubble.dataset.speaking = speech ? "true" : "false";
  bubble.dataset.utterance = speech ? speech.id : "";
  const earlier = said.slice(0, shown && said.length && said[said.length - 1] === shown ? -1 : said.length).reverse();
  $("said").replaceChildren(...earlier.map((text) => {
    const li = document.createElement("li"); li.textContent = text; return li;
  }));
  if (speech) {
    if (speech.id !== spoken) { spoken = speech.id; speak(speech); }
  } else if (before && before.speech) {
    stopMouth();
  }
}

// --- arrivals, departures, gestures -------------------------------------------------------------

let captionTimer = 0;
let arrivalShown = null;  // the ``at`` of the arrival already shown: an arrival is shown once

function showTransition(next) {
  const t = next.transition;
  const caption = $("transition");
  let line = "";
  let kind = "";
  if (t && t.kind === "arriving") {
    // News for a moment, once: only while the state says it is still an arrival (``until``, on the
    // daemon's clock, as ``time`` is), and not again on the next state of the same arrival.
    const left = (t.until || 0) - next.time;
    if (arrivalShown !== t.at && left > 0) {
      arrivalShown = t.at;
      line = `${next.companion} arrives${t.from ? " from " + t.from : ""}`;
      kind = "arriving";
      clearTimeout(captionTimer);
      captionTimer = setTimeout(() => {
        caption.textContent = "";
        body.dataset.transition = "";
      }, left * 1000);
    } else if (arrivalShown === t.at) {
      return;  // the arrival being shown goes on; its timer ends it
    }
  } else if (t && t.kind === "leaving") {
    line = `${next.companion} is leaving for ${t.to}`;
    kind = "leaving";
  } else if (t && t.kind === "left") {
    line = `the companion went to ${t.to}`;  // stays: it says why the body is empty
    kind = "left";
  }
  if (kind !== "arriving") clearTimeout(captionTimer);
  body.dataset.transition = kind;
  if (caption.textContent !== line) caption.textContent = line;
}

const GESTURES = { wave: "waves", nod: "nods", smile: "smiles", curious: "looks curious", vibrate: "vibrates" };

function showGesture(next) {
  const gesture = next.companion && next.animation ? GESTURES[next.animation] || next.animation : "";
  const text = gesture ? `${next.companion} ${gesture}` : "";
  if ($("gesture").textContent !== text) $("gesture").textContent = text;
}

// --- the voice, and the mouth in step with it --------------------------------------------------

function speak(speech) {
  stopMouth();
  if (!speech.audio) { mouthByText(speech); return; }
  voice.src = speech.audio;
  voice.onended = stopMouth;
  const playing = voice.play();
  if (playing && playing.then) {
    playing.then(() => mouthByAudio(speech)).catch(() => {
      $("sound").hidden = false;  // the browser wants a gesture before sound: offer one
      mouthByText(speech);
    });
  }
}

function enableSound(fromGesture) {
  // Routing the voice through Web Audio lets the mouth follow its loudness; a context the
  // browser keeps suspended (no gesture yet) would silence it, so it is only kept when running.
  if (!audioContext) {
    const Context = window.AudioContext || window.webkitAudioContext;
    if (!Context) return false;
    const context = new Context();
    if (context.state !== "running" && !fromGesture) { context.close(); return false; }
    audioContext = context;
    const source = audioContext.createMediaElementSource(voice);
    analyser = audioContext.createAnalyser();
    analyser.fftSize = 512;
    source.connect(analyser);
    analyser.connect(audioContext.destination);
  }
  audioContext.resume();
  $("sound").hidden = true;
  return true;
}

function setMouth(open) {
  const ry = 1 + 13 * Math.max(0, Math.min(1, open));
  $("mouth").setAttribute("ry", ry.toFixed(1));
}

function mouthByAudio(speech) {
  if (!analyser) {
    try { enableSound(false); } catch (e) { /* no Web Audio: the text rhythm drives the mouth */ }
  }
  if (!analyser) { mouthByText(speech); return; }
  const samples = new Uint8Array(analyser.fftSize);
  const frame = () => {
    analyser.getByteTimeDomainData(samples);
    let sum = 0;
    for (const s of samples) { const v = (s - 128) / 128; sum += v * v; }
    setMouth(Math.sqrt(sum / samples.length) * 5);
    if (!voice.paused && !voice.ended) mouthFrame = requestAnimationFrame(frame);
    else setMouth(0);
  };
  mouthFrame = requestAnimationFrame(frame);
}

function mouthByText(speech) {
  // Without sound, the mouth opens on each vowel group at the pace of the line's length.
  const beats = (speech.text.match(/[aeiouy]+/gi) || ["a"]).length;
  const start = performance.now();
  const total = speech.seconds * 1000;
  const frame = (now) => {
    const elapsed = now - start;
    if (elapsed >= total || !state || !state.speech || state.speech.id !== speech.id) { setMouth(0); return; }
    setMouth(Math.abs(Math.sin(Math.PI * beats * elapsed / total)));
    mouthFrame = requestAnimationFrame(frame);
  };
  mouthFrame = requestAnimationFrame(frame);
}

function stopMouth() {
  cancelAnimationFrame(mouthFrame);
  setMouth(0);
}

// --- the senses ------------------------------------------------------------------------------------

function answer(value) {
  if (state && state.asking) send({ type: "answer", value });
}

$("yes").addEventListener("click", () => answer("yes"));
$("no").addEventListener("click", () => answer("no"));
$("sound").addEventListener("click", () => { enableSound(true); if (voice.paused && state && state.speech) voice.play(); });
document.addEventListener("keydown", (event) => {
  if (event.target instanceof HTMLInputElement) return;
  if (event.key === "y") answer("yes");
  else if (event.key === "n") answer("no");
});
$("visitor-form").addEventListener("submit", (event) => {
  event.preventDefault();
  const name = $("visitor-name").value.trim();
  const present = $("visitor").getAttribute("aria-pressed") !== "true";
  send({ type: "visitor", name, present });
});
$("command-form").addEventListener("submit", (event) => {
  event.preventDefault();
  const text = $("command").value.trim();
  if (text) { send({ type: "command", text }); $("command").value = ""; }
});
document.addEventListener("pointerdown", () => { if (audioContext) audioContext.resume(); }, { once: true });

connect();
