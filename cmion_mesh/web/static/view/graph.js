// The mesh as a picture, and its timeline (loaded after view.js, whose `state` it draws).
//
// Graph: embodiments on a circle (1 to 32 without overlap), links between those that see each
// other, each companion a token resting on its host; a migration moves the token along its edge
// at a pace a person can follow (TRAVEL_MS, whatever the handshake took), the handshake's steps
// shown on the way with their real times. Timeline: everything seen on one time axis; a moment
// picked (click, or the slider with the keyboard) draws the mesh as it was then; a recording's
// timeline seeks the player instead. Nothing here runs while nothing moves: no timer, no polling.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
const TRAVEL_MS = 2400;
const STEPS = ["starting", "prepared", "incoming", "handed", "active", "released"];
const ENDED = new Set(["succeeded", "failed", "dropped"]);
const RING = 190;         // the ring's radius, at least (more when many nodes need room)
const NAME_CHARS = 18;    // longer names are cut on the picture (whole in their title and label)
const CHAR_W = 7.8;       // width of a character of a node's name, at most (13px, bold)

const graph = {
  frames: [],            // pictures of the mesh over time (the server's ``Model.frames``)
  seen: new Set(),       // migrations already shown (or there before the page): not travelled again
  travels: new Map(),    // companion -> [{attempt, started}] waiting or under way
  frame: 0,              // requestAnimationFrame of the travels, 0 when nothing moves
  playback: null,        // a recording's status, or null when live
  cursorFrame: 0,
};
stats.travels = [];      // each travel as it began: {companion, from, to, attempt}

function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(SVG, tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, String(value));
  }
  for (const child of children) if (child) node.append(child);
  return node;
}

// --- what to draw: now, or as it was at the moment picked ------------------------------------

function frameAt(t) {
  let found = null;
  for (const f of graph.frames) { if (f.time <= t) found = f; else break; }
  return found;
}

function scene() {
  // The embodiments ({name: {alive, inhabitant, card}}) and custody at the moment shown.
  const cards = state.embodiments;
  if (state.scrub === null || state.scrub === undefined) {
    const out = new Map();
    for (const [name, card] of cards) out.set(name, { alive: card.alive, inhabitant: (card.description || {}).inhabitant || null, card });
    return { nodes: out, custody: state.custody, at: null };
  }
  const f = frameAt(state.scrub);
  const out = new Map();
  if (f) for (const [name, [alive, inhabitant]] of Object.entries(f.embodiments)) out.set(name, { alive, inhabitant, card: cards.get(name) });
  return { nodes: out, custody: f ? f.custody : {}, at: state.scrub };
}

function shortName(name) {
  return name.length > NAME_CHARS ? name.slice(0, NAME_CHARS - 1) + "…" : name;
}

function layout(names) {
  // Nodes on a ring, radius at least 14 for up to 32 (the ring grows rather than the nodes
  // shrinking); neighbours are a chord apart and a node's radius stays under 0.36 of it. Names
  // outside the ring, turned along the radius beyond 10 nodes; the picture (viewBox) is as large
  // as that needs, and the page scales it.
  const n = names.length;
  const places = new Map();
  const ring = n > 1 ? Math.max(RING, 14 / 0.36 / (2 * Math.sin(Math.PI / n))) : 0;
  const chord = n > 1 ? 2 * ring * Math.sin(Math.PI / n) : 2 * RING;
  const r = Math.max(9, Math.min(34, chord * 0.36));
  const radial = n > 10;
  const longest = Math.max(4, ...names.map((name) => shortName(name).length + 3)) * CHAR_W;
  const half = ring + r + 10 + longest;
  const width = 2 * half, height = radial ? 2 * half : 2 * (ring + r + 34);
  names.forEach((name, i) => {
    const angle = n === 1 ? -Math.PI / 2 : -Math.PI / 2 + (2 * Math.PI * i) / n;
    places.set(name, { x: width / 2 + ring * Math.cos(angle), y: height / 2 + ring * Math.sin(angle), angle, r, radial });
  });
  places.viewBox = [0, 0, Math.round(width), Math.round(height)];
  return places;
}

function label(place, text, cls) {
  // Outside the ring, along the radius when there are many (they never cross each other then).
  const { x, y, angle, r, radial } = place;
  const d = r + 8;
  const lx = x + d * Math.cos(angle), ly = y + d * Math.sin(angle);
  if (radial) {
    const deg = (angle * 180) / Math.PI;
    const left = Math.cos(angle) < 0;
    return svg("text", { class: cls, x: lx, y: ly, "text-anchor": left ? "end" : "start", "dominant-baseline": "middle",
      transform: `rotate(${left ? deg + 180 : deg} ${lx} ${ly})`, text });
  }
  const c = Math.cos(angle), s = Math.sin(angle);
  const anchor = Math.abs(c) < 0.35 ? "middle" : c > 0 ? "start" : "end";
  const base = s > 0.35 ? "hanging" : s < -0.35 ? "auto" : "middle";
  return svg("text", { class: cls, x: lx, y: ly, "text-anchor": anchor, "dominant-baseline": base, text });
}

// --- the graph -----------------------------------------------------------------------------------

function drawGraph() {
  const root = $("graph");
  const { nodes, custody, at } = scene();
  const names = [...nodes.keys()].sort();
  const places = layout(names);
  graph.places = places;
  const links = svg("g", { class: "links" });
  const seeing = (a, b) => {
    const card = nodes.get(a).card;
    const seen = card && card.description && card.description.alive;
    return Array.isArray(seen) && seen.includes(b);
  };
  for (let i = 0; i < names.length; i++) {
    for (let j = i + 1; j < names.length; j++) {
      const a = names[i], b = names[j];
      if (!nodes.get(a).alive || !nodes.get(b).alive) continue;
      const ab = seeing(a, b), ba = seeing(b, a);
      if (!ab && !ba) continue;
      const p = places.get(a), q = places.get(b);
      links.append(svg("line", { class: `link${ab && ba ? "" : " one-way"}`, x1: p.x, y1: p.y, x2: q.x, y2: q.y,
        "data-a": a, "data-b": b, "data-mutual": String(ab && ba) },
      svg("title", { text: ab && ba ? `${a} and ${b} see each other` : `${ab ? a : b} sees ${ab ? b : a}, not the other way` })));
    }
  }
  const hosts = new Map();  // companion -> hosts alive
  for (const [name, node] of nodes) if (node.alive && node.inhabitant) hosts.set(node.inhabitant, [...(hosts.get(node.inhabitant) || []), name]);
  const holding = new Map();  // embodiment -> [[companion, epoch]]
  for (const [companion, holders] of Object.entries(custody || {})) {
    for (const [holder, epoch] of Object.entries(holders)) holding.set(holder, [...(holding.get(holder) || []), [companion, epoch]]);
  }
  const group = svg("g", { class: "nodes" });
  for (const name of names) {
    const node = nodes.get(name);
    const place = places.get(name);
    const duplicate = node.inhabitant && (hosts.get(node.inhabitant) || []).length > 1;
    const claims = node.card && node.card.description && (node.card.description.duplicates || []).length > 0;
    const held = holding.get(name) || [];
    const what = [node.alive ? "alive" : "gone", node.inhabitant ? `inhabited by ${node.inhabitant}` : "empty"];
    if (held.length) what.push(`custody of ${held.map(([c, e]) => `${c} (epoch ${e})`).join(", ")}`);
    if (duplicate) what.push(`DUPLICATE: ${node.inhabitant} lives on more than one embodiment`);
    if (claims) what.push("another daemon claims this name");
    const g = svg("g", {
      class: `node${node.alive ? " alive" : " gone"}${node.inhabitant ? " inhabited" : ""}${duplicate || claims ? " duplicate" : ""}`
        + `${name === state.selected ? " selected" : ""}`,
      "data-embodiment": name, "data-alive": String(node.alive), "data-inhabitant": node.inhabitant || "",
      "data-custody": held.map(([c, e]) => `${c}:${e}`).join(" "), "data-duplicate": String(Boolean(duplicate || claims)),
      "data-x": place.x.toFixed(1), "data-y": place.y.toFixed(1), "data-r": place.r.toFixed(1),
      tabindex: at === null ? 0 : -1, role: "button", "aria-label": `${name}: ${what.join("; ")}`,
      onclick: () => select(name),
      onkeydown: (e) => { if (e.key === "Enter" || e.key === " ") { e.preventDefault(); select(name); } },
    }, svg("title", { text: `${name}: ${what.join("; ")}` }),
    held.length ? svg("circle", { class: "custody-ring", cx: place.x, cy: place.y, r: place.r + 5 }) : null,
    svg("circle", { class: "disc", cx: place.x, cy: place.y, r: place.r }),
    label(place, shortName(name) + (duplicate || claims ? " ⚠" : ""), "name"));
    group.append(g);
  }
  const tokens = svg("g", { class: "tokens" });
  root.setAttribute("viewBox", (names.length ? places.viewBox : [0, 0, 800, 300]).join(" "));
  root.replaceChildren(links, svg("g", { class: "travel", id: "travel" }), group, tokens);
  $("graph-when").textContent = at === null ? `${names.filter((n) => nodes.get(n).alive).length} alive`
    : `as it was at ${clock(at)}`;
  $("graph").dataset.scrub = at === null ? "" : String(at);
  if (!names.length) root.append(svg("text", { x: 400, y: 150, "text-anchor": "middle", class: "empty-note", text: "no embodiment seen yet" }));
  const warnings = [...hosts].filter(([, h]) => h.length > 1).map(([c, h]) => `DUPLICATE: ${c} lives on ${h.join(" and ")}`);
  $("graph-warning").textContent = warnings.join(" · ");
  drawTokens();
  drawNodeInfo();
}

function companionsIn(nodes) {
  const names = new Set();
  for (const node of nodes.values()) if (node.inhabitant) names.add(node.inhabitant);
  for (const m of state.migrations.values()) if (m.companion) names.add(m.companion);
  return [...names].sort();
}

function rank(step) { const i = STEPS.indexOf(step); return i < 0 ? 0 : i; }

function migrationEnd(m) {
  return ENDED.has(m.status) && m.steps.length ? Math.max(...m.steps.map((s) => s.received || s.time)) : Infinity;
}

// Where a companion is drawn: {x, y, state, from, to, progress, attempt}.
function tokenPlace(companion, nodes) {
  const places = graph.places;
  const travel = (graph.travels.get(companion) || [])[0];
  if (state.scrub === null && travel && travel.started) {
    const m = state.migrations.get(travel.attempt);
    const p = places.get(m.source), q = places.get(m.target);
    if (p && q) {
      const progress = travelProgress(travel, m);
      const along = m.status === "failed" || m.status === "dropped" ? (progress < 0.5 ? progress : 1 - progress) : progress;
      return { x: p.x + (q.x - p.x) * along, y: p.y + (q.y - p.y) * along, state: "travelling", from: m.source, to: m.target,
        progress, attempt: m.attempt, migration: m };
    }
  }
  if (state.scrub !== null) {
    // As it was: on the edge of a migration under way at that moment, at its last step by then.
    const t = state.scrub;
    for (const m of state.migrations.values()) {
      if (m.companion !== companion || !m.steps.length) continue;
      const begun = m.steps[0].received || m.steps[0].time;
      if (begun <= t && t < migrationEnd(m)) {
        const done = m.steps.filter((s) => (s.received || s.time) <= t);
        const progress = Math.max(...done.map((s) => rank(s.step))) / (STEPS.length - 1);
        const p = places.get(m.source), q = places.get(m.target);
        if (p && q) return { x: p.x + (q.x - p.x) * progress, y: p.y + (q.y - p.y) * progress, state: "travelling",
          from: m.source, to: m.target, progress, attempt: m.attempt, migration: m, upTo: t };
      }
    }
  }
  const host = [...nodes].find(([, node]) => node.alive && node.inhabitant === companion);
  if (host) {
    const p = places.get(host[0]);
    return { x: p.x, y: p.y, state: "resting", at: host[0] };
  }
  return null;
}

function arrived(m) {
  // Over, or the target lives (its ``active``): the source's last word may come later, or never
  // (a recording that ends there).
  return ENDED.has(m.status) || m.steps.some((s) => s.step === "active");
}

function travelProgress(travel, m) {
  const elapsed = (now() - travel.started) / TRAVEL_MS;
  if (arrived(m)) return Math.min(1, elapsed);
  // Still under way: no further than the steps seen so far say.
  const reached = Math.max(0, ...m.steps.map((s) => rank(s.step))) / (STEPS.length - 1);
  return Math.min(elapsed, reached);
}

function drawTokens() {
  const root = $("graph");
  const tokens = root.querySelector(".tokens");
  const travelGroup = root.querySelector("#travel");
  if (!tokens) return;
  const { nodes } = scene();
  const drawn = [];
  const route = [];
  for (const companion of companionsIn(nodes)) {
    const place = tokenPlace(companion, nodes);
    if (!place) continue;
    const r = Math.max(6, Math.min(14, ((graph.places.values().next().value || {}).r || 20) * 0.55));
    const g = svg("g", { class: `token ${place.state}`, "data-companion": companion, "data-state": place.state,
      "data-at": place.at || "", "data-from": place.from || "", "data-to": place.to || "",
      "data-progress": place.progress === undefined ? "" : place.progress.toFixed(3), "data-attempt": place.attempt || "",
      "data-x": place.x.toFixed(1), "data-y": place.y.toFixed(1), transform: `translate(${place.x.toFixed(1)} ${place.y.toFixed(1)})`,
      role: "img", "aria-label": place.state === "resting" ? `${companion} lives on ${place.at}` : `${companion} travelling from ${place.from} to ${place.to}` },
    svg("circle", { r }),
    // Travelling, the name is beside the graph (with the steps): the steps' labels have the edge.
    place.state === "resting" ? svg("text", { class: "token-name", y: -r - 4, "text-anchor": "middle", text: companion }) : null);
    drawn.push(g);
    if (place.migration) route.push(...stepMarks(place));
  }
  tokens.replaceChildren(...drawn);
  travelGroup.replaceChildren(...route);
  if (!route.length) $("travel-steps").hidden = true;
}

function stepMarks(place) {
  // The handshake's steps along the edge (between the two discs), each at its place in the
  // handshake's order, shown once the token has passed it, with its time since the start; the
  // same, in words, beside the graph.
  const m = place.migration;
  const p = graph.places.get(m.source), q = graph.places.get(m.target);
  const start = m.steps.length ? m.steps[0].time : 0;
  const out = [svg("line", { class: `route ${m.status}`, x1: p.x, y1: p.y, x2: q.x, y2: q.y })];
  const dx = q.x - p.x, dy = q.y - p.y, len = Math.hypot(dx, dy) || 1;
  const from = p.r / len, to = 1 - q.r / len;  // the edge between the discs, as fractions
  const shown = [];
  m.steps.forEach((s, i) => {
    const f = STEPS.includes(s.step) ? rank(s.step) / (STEPS.length - 1) : 1;
    if (place.upTo !== undefined ? (s.received || s.time) > place.upTo : f > place.progress + 1e-6) return;
    const along = from + (to - from) * f;
    const x = p.x + dx * along, y = p.y + dy * along;
    const side = i % 2 ? 1 : -1;  // alternate sides of the edge: neighbouring labels do not meet
    const tx = x + (side * 24 * -dy) / len, ty = y + (side * 24 * dx) / len;
    const ms = Math.round((s.time - start) * 1000);
    shown.push(`${s.step} on ${s.embodiment}: +${ms} ms`);
    out.push(svg("g", { class: "step-mark", "data-step": s.step },
      svg("circle", { cx: x, cy: y, r: 4 }),
      svg("text", { x: tx, y: ty, "text-anchor": "middle", "dominant-baseline": "middle", text: `${s.step} +${ms} ms` })));
  });
  const list = $("travel-steps");
  list.hidden = false;
  list.replaceChildren(el("h3", { text: `${m.companion}: ${m.source} → ${m.target}` }),
    el("ol", {}, ...shown.map((text) => el("li", { text }))));
  return out;
}

// --- travels: each migration once, one after the other per companion ------------------------------

function migrationSeen(m, fromSnapshot) {
  if (graph.seen.has(m.attempt)) return;
  graph.seen.add(m.attempt);
  if (fromSnapshot || !m.source || !m.target || !m.companion) return;
  const queue = graph.travels.get(m.companion) || [];
  queue.push({ attempt: m.attempt, started: 0 });
  graph.travels.set(m.companion, queue);
  animate();
}

function animate() {
  if (graph.frame) return;
  const tick = () => {
    graph.frame = 0;
    let moving = false;
    for (const [companion, queue] of graph.travels) {
      while (queue.length) {
        const travel = queue[0];
        const m = state.migrations.get(travel.attempt);
        if (!m) { queue.shift(); continue; }
        if (!travel.started) {
          travel.started = now();
          stats.travels.push({ companion, from: m.source, to: m.target, attempt: m.attempt });
        }
        if (arrived(m) && now() - travel.started >= TRAVEL_MS) { queue.shift(); continue; }
        moving = true;
        break;
      }
      if (!queue.length) graph.travels.delete(companion);
    }
    drawTokens();
    if (moving) graph.frame = requestAnimationFrame(tick);
  };
  graph.frame = requestAnimationFrame(tick);
}

function drawNodeInfo() {
  const box = $("node-info");
  const card = state.selected && state.embodiments.get(state.selected);
  if (!card) { box.replaceChildren(el("p", { class: "note", text: "Pick an embodiment (click it, or Tab to it and press Enter) to see its competencies." })); return; }
  const d = card.description || {};
  const rows = [["state", card.alive ? "alive" : "gone"], ["inhabitant", d.inhabitant || "empty"],
    ["competencies", (d.competency_types || []).join(", ") || "none"], ["minds", (d.minds || []).join(", ") || "none"],
    ["actions", (d.actions || []).join("; ") || "none"], ["sees", (d.alive || []).filter((n) => n !== card.name).join(", ") || "nobody"]];
  if (d.host) rows.push(["process", `${d.host} pid ${d.pid}`]);
  box.replaceChildren(el("h3", { text: card.name }),
    el("dl", {}, ...rows.flatMap(([k, v]) => [el("dt", { text: k }), el("dd", { text: v })])));
}

// --- the timeline ----------------------------------------------------------------------------------

const KINDS = {
  migration: "migration", action: "action", plan: "plan", wm: "world model", person: "person arrives", mesh: "embodiment",
};

function timelineItems() {
  const items = [];
  for (const e of state.events) {
    const kind = eventKind(e);
    if (kind) items.push({ time: e.received || e.time, kind, text: eventLine(e) });
  }
  let before = null;
  for (const f of graph.frames) {
    const alive = Object.entries(f.embodiments).filter(([, [a]]) => a).map(([n]) => n).sort().join(",");
    if (before !== null && alive !== before) items.push({ time: f.time, kind: "mesh", text: `alive: ${alive || "nobody"}` });
    before = alive;
  }
  return items;
}

function eventKind(e) {
  if (e.component === "migration" && e.name === "MigrationStarting") return "migration";
  if (e.component === "manager" && e.name.startsWith("Action") && e.name !== "ActionAttempt") return "action";
  if (e.component === "execution" && e.name.startsWith("Plan")) return "plan";
  if (e.component === "wm") {
    const d = e.data || {};
    return d.name === "present" && d.value === true ? "person" : "wm";
  }
  return null;
}

function axis() {
  if (graph.playback) return [graph.playback.start, Math.max(graph.playback.end, graph.playback.start + 0.001)];
  const times = [...graph.frames.map((f) => f.time), ...state.events.map((e) => e.received || e.time)];
  if (!times.length) return [0, 1];
  const lo = Math.min(...times), hi = Math.max(...times);
  return [lo, Math.max(hi, lo + 0.001)];
}

function drawTimeline() {
  oncePerFrame(drawTimelineNow);
}

function drawTimelineNow() {
  const root = $("timeline");
  const [lo, hi] = axis();
  const width = 1000;
  const x = (t) => ((t - lo) / (hi - lo)) * width;
  const marks = [];
  for (const m of state.migrations.values()) {
    if (!m.steps.length) continue;
    const a = m.steps[0].received || m.steps[0].time;
    const b = Math.max(...m.steps.map((s) => s.received || s.time));
    marks.push(svg("rect", { class: `mark migration ${m.status}`, x: x(a) - 2, y: 2, width: Math.max(4, x(b) - x(a) + 4), height: 14,
      "data-kind": "migration", "data-time": a, "data-attempt": m.attempt },
    svg("title", { text: `${clock(a)} ${m.companion} ${m.source} → ${m.target}: ${m.status}` })));
  }
  const rows = { action: 20, plan: 20, wm: 32, person: 32, mesh: 44 };
  for (const item of timelineItems()) {
    if (item.kind === "migration") continue;
    marks.push(svg("rect", { class: `mark ${item.kind}`, x: x(item.time) - 1.5, y: rows[item.kind], width: 3, height: 10,
      "data-kind": item.kind, "data-time": item.time }, svg("title", { text: `${clock(item.time)} ${item.text}` })));
  }
  const at = cursorTime();
  marks.push(svg("line", { class: "cursor", id: "timeline-cursor", x1: x(at), x2: x(at), y1: 0, y2: 56 }));
  root.replaceChildren(...marks);
  root.dataset.start = String(lo);
  root.dataset.end = String(hi);
  const slider = $("scrub");
  slider.value = String(Math.round(((at - lo) / (hi - lo)) * 1000));
  slider.setAttribute("aria-valuetext", state.scrub === null && !graph.playback ? "live" : clock(at));
  $("timeline-span").textContent = graph.frames.length || state.events.length || graph.playback ? `${clock(lo)} – ${clock(hi)}` : "nothing seen yet";
}

function cursorTime() {
  const [lo, hi] = axis();
  if (graph.playback) {
    const p = graph.playback;
    const position = p.playing ? p.position + ((Date.now() / 1000) - p.at) * p.speed : p.position;
    return Math.min(hi, Math.max(lo, position));
  }
  return state.scrub === null ? hi : state.scrub;
}

function pick(t) {
  // A moment picked on the timeline: a recording seeks there; a live view draws the mesh as it was.
  if (graph.playback) {
    send({ type: "playback", action: "seek", position: t });
    return;
  }
  const [, hi] = axis();
  state.scrub = t >= hi ? null : t;
  $("live").disabled = state.scrub === null;
  drawGraph();
  drawTimelineNow();
}

function live() {
  state.scrub = null;
  $("live").disabled = true;
  drawGraph();
  drawTimelineNow();
}

$("timeline").addEventListener("click", (e) => {
  const box = $("timeline").getBoundingClientRect();
  const [lo, hi] = axis();
  pick(lo + ((e.clientX - box.left) / box.width) * (hi - lo));
});
$("scrub").addEventListener("input", () => {
  const [lo, hi] = axis();
  pick(lo + (Number($("scrub").value) / 1000) * (hi - lo));
});
$("live").addEventListener("click", live);

// --- playing a recording ---------------------------------------------------------------------------

function setPlayback(status) {
  graph.playback = status;
  $("playback").hidden = !status;
  $("live").hidden = Boolean(status);
  if (!status) return;
  $("mode").textContent = "a recording";
  $("connection").textContent = $("connection").dataset.state === "open" ? "playing" : $("connection").textContent;
  $("play").textContent = status.playing ? "Pause" : "Play";
  $("play").setAttribute("aria-pressed", String(!status.playing));
  $("speed").value = String(status.speed);
  $("playback-note").textContent = `${status.file}${status.truncated ? " (read in part: truncated)" : ""}: ${status.played} of ${status.messages} messages`;
  $("playback").dataset.playing = String(status.playing);
  $("playback").dataset.position = String(status.position);
  drawTimeline();
  cancelAnimationFrame(graph.cursorFrame);
  if (status.playing) {
    // The cursor moves with the recording's clock while it plays, and stops with it.
    const move = () => {
      const [lo, hi] = axis();
      const cursor = $("timeline-cursor");
      if (cursor) { const x = ((cursorTime() - lo) / (hi - lo)) * 1000; cursor.setAttribute("x1", x); cursor.setAttribute("x2", x); }
      if (graph.playback && graph.playback.playing && cursorTime() < hi) graph.cursorFrame = requestAnimationFrame(move);
    };
    graph.cursorFrame = requestAnimationFrame(move);
  }
}

$("play").addEventListener("click", () => {
  if (graph.playback) send({ type: "playback", action: graph.playback.playing ? "pause" : "play" });
});
$("speed").addEventListener("change", () => send({ type: "playback", action: "speed", speed: Number($("speed").value) }));

Object.assign(window.cmionView, { graph, drawGraph, pick, live, layout });
