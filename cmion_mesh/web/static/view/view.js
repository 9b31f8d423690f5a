// The live view's page: everything arrives over one WebSocket, pushed by the server as it
// happens (a snapshot first, then batches of changes and events); the page never polls.
"use strict";

const EVENTS_KEPT = 2000;   // events held for the filters
const EVENT_ROWS = 500;     // events drawn
const DRAWN_KEPT = 5000;    // draw times kept for tests and benchmarks

const state = {
  mesh: "", allowActions: false, dropped: 0,
  embodiments: new Map(), custody: {}, migrations: new Map(), plans: new Map(),
  events: [], selected: null, scrub: null,
  trees: { bb: new Map(), wm: new Map() },
};
// When each thing was drawn (ms since the epoch): the page's half of a latency measurement.
const stats = { messages: 0, drawn: [], treeDrawn: new Map(), lastSnapshot: 0 };
let socket = null;
let retry = 500;
let actionCounter = 0;

const $ = (id) => document.getElementById(id);
const now = () => performance.timeOrigin + performance.now();

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children) if (child !== null && child !== undefined) node.append(child);
  return node;
}

function flash(node) {
  node.classList.remove("changed");
  void node.offsetWidth; // restart the animation
  node.classList.add("changed");
}

function short(value, limit = 200) {
  const text = typeof value === "string" ? value : JSON.stringify(value);
  return text.length > limit ? text.slice(0, limit) + "…" : text;
}

function clock(seconds) {
  const d = new Date(seconds * 1000);
  return d.toLocaleTimeString([], { hour12: false }) + "." + String(d.getMilliseconds()).padStart(3, "0");
}

// --- the connection ------------------------------------------------------------------------

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  socket = new WebSocket(`${scheme}://${location.host}/ws`);
  setConnection("connecting");
  socket.onopen = () => {
    retry = 500;
    setConnection("open");
    if (state.selected) send({ type: "select", embodiment: state.selected });
  };
  socket.onmessage = (message) => receive(JSON.parse(message.data));
  socket.onclose = () => {
    setConnection("closed");
    setTimeout(connect, retry);  // the view restarted or the link dropped: come back
    retry = Math.min(retry * 2, 10000);
  };
}

function setConnection(text) {
  const badge = $("connection");
  badge.dataset.state = text;
  badge.textContent = text === "open" ? "live" : text;
}

function send(message) {
  if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
}

function receive(message) {
  stats.messages += 1;
  if (message.type === "snapshot") snapshot(message);
  else if (message.type === "batch") {
    for (const change of message.changes) applyChange(change);
    for (const event of message.events) addEvent(event);
    setDropped(message.dropped);
  }
}

function snapshot(message) {
  state.mesh = message.mesh;
  state.allowActions = message.allow_actions;
  $("mesh").textContent = message.mesh;
  const mode = $("mode");
  mode.textContent = message.allow_actions ? "actions allowed" : "read-only";
  mode.classList.toggle("actions", message.allow_actions);
  $("actions").hidden = !message.allow_actions;
  state.embodiments = new Map(message.embodiments.map((card) => [card.name, card]));
  state.custody = message.custody;
  state.migrations = new Map(message.migrations.map((m) => [m.attempt, m]));
  state.plans = new Map(message.plans.map((p) => [p.key, p]));
  state.events = [];
  actionStarts.clear();
  $("events").tBodies[0].replaceChildren();
  for (const event of message.events) addEvent(event);
  setDropped(message.dropped);
  graph.frames = message.frames || [];
  // What the snapshot holds is the past (or, after a seek, the recording's past): not travelled again.
  graph.seen.clear();
  graph.travels.clear();
  for (const m of state.migrations.values()) migrationSeen(m, true);
  setPlayback(message.playback || null);
  drawEmbodiments();
  drawMigrations();
  drawPlans();
  drawGraph();
  drawTimeline();
  if (message.trees) setTrees(message.trees);
  stats.lastSnapshot = now();
}

function setDropped(count) {
  state.dropped = count;
  const badge = $("dropped");
  badge.hidden = !count;
  badge.textContent = `${count} events dropped (slow page)`;
}

function applyChange(change) {
  switch (change.type) {
    case "embodiment":
      state.embodiments.set(change.card.name, change.card);
      drawEmbodiments();
      scheduleGraph();
      break;
    case "frame":
      graph.frames.push(change.frame);
      if (graph.frames.length > 2000) graph.frames.splice(0, graph.frames.length - 2000);
      scheduleGraph();
      drawTimeline();
      break;
    case "playback":
      setPlayback(change.playback);
      break;
    case "custody":
      if (Object.keys(change.holders).length) state.custody[change.companion] = change.holders;
      else delete state.custody[change.companion];
      drawCompanions();
      scheduleGraph();
      break;
    case "migration":
      state.migrations.set(change.migration.attempt, change.migration);
      while (state.migrations.size > 50) state.migrations.delete(state.migrations.keys().next().value);
      drawMigrations();
      migrationSeen(change.migration, false);
      scheduleGraph();
      drawTimeline();
      break;
    case "plan":
      state.plans.delete(change.plan.key);
      state.plans.set(change.plan.key, change.plan);
      while (state.plans.size > 100) state.plans.delete(state.plans.keys().next().value);
      drawPlans();
      break;
    case "trees":
      setTrees(change);
      break;
    case "tree":
      if (change.embodiment === state.selected) setTreeEntry(change.store, change.path, change.entry, true);
      break;
    case "action_result":
      drawActionResult(change);
      break;
    case "error":
      console.warn("view:", change.reason);
      break;
  }
}

// --- embodiments and companions --------------------------------------------------------------

function select(name) {
  state.selected = name;
  $("selected-name").textContent = name;
  for (const store of ["bb", "wm"]) { state.trees[store].clear(); $(`tree-${store}`).replaceChildren(); }
  $("tree-note").textContent = "reading…";
  send({ type: "select", embodiment: name });
  drawEmbodiments();
  scheduleGraph();
}

// Each drawing at most once a frame, however many changes one message (or batch) brings: the graph
// here, the timeline (graph.js).
const framesQueued = new Set();
function oncePerFrame(draw) {
  if (framesQueued.has(draw)) return;
  framesQueued.add(draw);
  requestAnimationFrame(() => { framesQueued.delete(draw); draw(); });
}

function scheduleGraph() {
  oncePerFrame(drawGraph);
}

function companionsKnown() {
  const names = new Set(Object.keys(state.custody));
  for (const card of state.embodiments.values()) {
    const who = card.description && card.description.inhabitant;
    if (who) names.add(who);
  }
  return [...names].sort();
}

function drawEmbodiments() {
  const cards = [...state.embodiments.values()].sort((a, b) => (b.alive - a.alive) || a.name.localeCompare(b.name));
  const alive = cards.filter((c) => c.alive).length;
  $("embodiment-count").textContent = `${alive} alive`;
  const companions = companionsKnown();
  $("embodiments").replaceChildren(...cards.map((card) => drawCard(card, companions)));
  const filter = $("filter-embodiment");
  const chosen = filter.value;
  filter.replaceChildren(el("option", { value: "", text: "all" }),
    ...cards.map((c) => el("option", { value: c.name, text: c.name, selected: c.name === chosen })));
  drawCompanions();
}

function drawCard(card, companions) {
  const d = card.description || {};
  const inhabitant = d.inhabitant
    ? el("span", { class: "inhabitant", text: d.inhabitant, title: "the companion living here" })
    : el("span", { class: "empty", text: card.alive ? "empty" : "left" });
  const details = [];
  if (d.competency_types && d.competency_types.length) details.push("competencies: " + d.competency_types.join(", "));
  if (d.minds && d.minds.length) details.push("minds: " + d.minds.join(", "));
  if (d.actions && d.actions.length) details.push("actions: " + d.actions.join("; "));
  if (d.host) details.push(`${d.host} pid ${d.pid}` + (d.version ? ` · ${d.version}` : ""));
  if (card.error) details.push("⚠ " + card.error);
  const node = el("div", {
    class: `card ${card.alive ? "alive" : "gone"}${card.name === state.selected ? " selected" : ""}`,
    "data-embodiment": card.name, "data-alive": String(card.alive), "data-inhabitant": d.inhabitant || "",
    onclick: () => select(card.name),
  },
  el("div", { class: "title" }, el("span", { class: "dot" }), el("span", { class: "name", text: card.name }), inhabitant),
  el("div", { class: "details", text: details.join(" · ") }));
  if (state.allowActions && card.alive) node.append(actionForm(card, companions));
  return node;
}

function actionForm(card, companions) {
  const input = el("input", { placeholder: "action and parameters", "aria-label": `action for ${card.name}` });
  const form = el("form", { onsubmit: (e) => {
    e.preventDefault();
    const words = input.value.trim().split(/\s+/).filter(Boolean);
    if (words.length) act(card.name, words[0], words.slice(1));
  } }, input, el("button", { type: "submit", text: "act" }));
  const inhabitant = card.description && card.description.inhabitant;
  for (const companion of companions) {
    if (companion !== inhabitant) {
      form.append(el("button", { type: "button", class: "migrate", text: `bring ${companion} here`,
        onclick: (e) => { e.stopPropagation(); migrate(companion, card.name); } }));
    }
  }
  form.addEventListener("click", (e) => e.stopPropagation());
  return form;
}

function act(embodiment, name, parameters) {
  const id = `a${++actionCounter}`;
  drawActionResult({ id, action: "act", status: "asked", reason: `${embodiment}: ${[name, ...parameters].join(" ")}` });
  send({ type: "act", id, embodiment, name, parameters });
  return id;
}

function migrate(companion, target) {
  const id = `a${++actionCounter}`;
  drawActionResult({ id, action: "migrate", status: "asked", reason: `${companion} → ${target}` });
  send({ type: "migrate", id, companion, target });
  return id;
}

function drawActionResult(result) {
  $("actions").hidden = false;
  const list = $("action-results");
  let node = list.querySelector(`[data-id="${CSS.escape(String(result.id))}"]`);
  if (!node) {
    node = el("li", { class: "action-result", "data-id": result.id });
    list.prepend(node);
    while (list.children.length > 20) list.lastElementChild.remove();
  }
  node.dataset.status = result.status;
  if (result.status === "asked") node.dataset.what = result.reason;
  const reason = result.status === "asked" ? "" : result.reason;
  node.textContent = `${result.action} ${node.dataset.what || ""}: ${result.status}${reason ? ` (${reason})` : ""}`;
}

function drawCompanions() {
  const rows = companionsKnown().map((companion) => {
    const hosts = [...state.embodiments.values()].filter((c) => c.alive && c.description && c.description.inhabitant === companion)
      .map((c) => c.name);
    const holders = state.custody[companion] || {};
    const custody = Object.entries(holders).map(([h, e]) => `${h} (epoch ${e})`).join(", ");
    const where = hosts.length ? `lives on ${hosts.join(" and ")}` : "in transit";
    return el("li", { "data-companion": companion, "data-host": hosts.join(",") },
      el("strong", { text: companion }), ` ${where}`,
      custody ? el("span", { class: "note", text: ` · custody: ${custody}` }) : null,
      hosts.length > 1 ? el("strong", { class: "bad", text: " DUPLICATE" }) : null);
  });
  $("companions").replaceChildren(...(rows.length ? rows : [el("li", { class: "note", text: "no companion seen" })]));
}

// --- migrations and plans ----------------------------------------------------------------------

function drawMigrations() {
  const items = [...state.migrations.values()].reverse().map((m) => {
    const start = m.steps.length ? m.steps[0].time : 0;
    return el("li", { class: "migration", "data-attempt": m.attempt, "data-status": m.status, "data-companion": m.companion },
      el("div", {}, el("strong", { text: m.companion || "?" }), ` ${m.source || "?"} → ${m.target || "?"} `,
        el("span", { class: "note", text: m.status + (m.reason ? `: ${m.reason}` : "") })),
      el("div", { class: "steps" }, ...m.steps.map((s) => el("span", {
        class: "step", "data-step": s.step, title: `${s.embodiment} at ${clock(s.time)}`,
        text: `${s.step} @${s.embodiment} +${Math.round((s.time - start) * 1000)} ms` }))));
  });
  $("migrations").replaceChildren(...(items.length ? items : [el("li", { class: "note", text: "none seen yet" })]));
}

function drawPlans() {
  const plans = [...state.plans.values()].sort((a, b) => (a.state !== "running") - (b.state !== "running")).slice(0, 40);
  const items = plans.map((p) => el("li", { class: "plan", "data-plan": p.key, "data-state": p.state },
    el("div", {}, el("strong", { text: p.embodiment }), ` ${p.action || p.run_id} `,
      el("span", { class: "note", text: p.state + (p.reason ? `: ${p.reason}` : "") })),
    el("div", { class: "steps" }, ...Object.entries(p.steps).map(([id, s]) => el("span", {
      class: "step", "data-status": s.status, title: s.reason || s.competency || "",
      text: `${id}${s.type ? ` (${s.type})` : ""}: ${s.status}` })))));
  $("plans").replaceChildren(...(items.length ? items : [el("li", { class: "note", text: "no plan seen yet" })]));
}

// --- the selected embodiment's trees ------------------------------------------------------------

function setTrees(message) {
  if (message.embodiment !== state.selected) return;
  for (const store of ["bb", "wm"]) {
    state.trees[store].clear();
    $(`tree-${store}`).replaceChildren();
    for (const [path, entry] of message.stores[store]) setTreeEntry(store, path, entry, false);
  }
  const notes = [];
  if (!message.ready) notes.push("reading…");
  if (message.truncated) notes.push("too many entries: some are left out");
  if (message.error) notes.push(message.error);
  $("tree-note").textContent = notes.join(" · ");
}

function treeNode(store, path) {
  const nodes = state.trees[store];
  let node = nodes.get(path);
  if (node) return node;
  const slash = path.lastIndexOf("/");
  const parentList = slash < 0 ? $(`tree-${store}`) : treeNode(store, path.slice(0, slash)).querySelector(":scope > ul");
  const name = path.slice(slash + 1);
  node = el("li", { class: "container", "data-path": path, "data-name": name },
    el("span", { class: "name", text: name }), el("span", { class: "value" }), el("ul"));
  const after = [...parentList.children].find((li) => li.dataset.name > name);
  parentList.insertBefore(node, after || null);
  nodes.set(path, node);
  return node;
}

function setTreeEntry(store, path, entry, changed) {
  const nodes = state.trees[store];
  if (entry === null) {
    for (const key of [...nodes.keys()]) {
      if (key === path || key.startsWith(path + "/")) {
        if (key === path) nodes.get(key).remove();
        nodes.delete(key);
      }
    }
  } else {
    const node = treeNode(store, path);
    const value = node.querySelector(":scope > .value");
    if (entry.kind === "property") {
      node.className = "property";
      value.textContent = JSON.stringify(entry.value);
      if (entry.persistent) value.append(el("span", { class: "persistent", text: " (persistent)" }));
    } else {
      node.className = "container";
      value.textContent = entry.type ? ` ${entry.type}` : "";
    }
    if (changed) flash(node);
  }
  stats.treeDrawn.set(`${store}/${path}`, { at: now(), value: entry && entry.value });
}

// --- events ------------------------------------------------------------------------------------

function matches(event) {
  const embodiment = $("filter-embodiment").value;
  const component = $("filter-component").value.trim().toLowerCase();
  const name = $("filter-name").value.trim().toLowerCase();
  return (!embodiment || event.embodiment === embodiment)
    && (!component || event.component.toLowerCase().includes(component))
    && (!name || event.name.toLowerCase().includes(name));
}

// One line a person reads, per event; the JSON is one click away (the row's "JSON").
const actionStarts = new Map();  // action id -> when it started (for "succeeded in 2.3 s")

function seconds(delta) {
  return delta < 1 ? `${Math.round(delta * 1000)} ms` : `${delta.toFixed(1)} s`;
}

function value(v) {
  return typeof v === "string" ? v : JSON.stringify(v);
}

function eventLine(e) {
  const d = e.data && typeof e.data === "object" ? e.data : {};
  const who = e.embodiment;
  const words = (name, params) => [name, ...(Array.isArray(params) ? params : [])].join(" ");
  switch (e.component) {
    case "manager": {
      const action = words(d.name, d.parameters);
      if (e.name === "ActionStarted") return `${who}: ${action} started`;
      if (e.name === "ActionAttempt") return `${who}: ${action}, attempt ${d.attempt}${ruleText(d.rule)}`;
      const status = d.status || e.name.replace(/^Action/, "").toLowerCase();
      const began = actionStarts.get(`${who}/${d.action_id}`);
      const took = began !== undefined ? ` in ${seconds(e.time - began)}` : "";
      return `${who}: ${action} ${status}${took}${ruleText(d.rule)}${d.reason ? `: ${d.reason}` : ""}`;
    }
    case "execution": {
      if (e.name === "PlanStarted") return `${who}: plan for ${d.action} started (${d.steps} step${d.steps === 1 ? "" : "s"})`;
      if (e.name.startsWith("Plan")) return `${who}: plan for ${d.action || d.run_id} ${e.name.slice(4).toLowerCase()}${d.reason ? `: ${d.reason}` : ""}`;
      if (e.name.startsWith("Step")) {
        return `${who}: step ${d.step} ${d.type || ""}${d.competency ? ` (${d.competency})` : ""} ${e.name.slice(4).toLowerCase()}`
          + `${d.reason ? `: ${d.reason}` : ""}`;
      }
      break;
    }
    case "migration": {
      const c = d.companion || "the companion";
      const epoch = d.epoch !== undefined ? ` (epoch ${d.epoch})` : "";
      if (e.name === "MigrationStarting") return `${who}: ${c} leaves for ${d.target}`;
      if (e.name === "MigrationStep") return `${who}: ${c}'s handshake with ${d.peer}: ${d.step}${epoch}`;
      if (e.name === "MigrationOccurred") {
        const why = typeof d.why === "string" && d.why.startsWith("arrived ") ? d.why : `arrived${d.why ? ` (${d.why})` : ""}`;
        return `${who}: ${c} ${why}${epoch}`;
      }
      if (e.name === "MigrationSucceeded") return `${who}: ${c} handed over to ${d.target}${epoch}`;
      if (e.name === "MigrationFailed") return `${who}: ${c} could not go to ${d.target || "?"}${d.reason ? `: ${d.reason}` : ""}`;
      if (e.name === "MigrationDropped") return `${who}: ${c}'s arrival from ${d.source || "?"} dropped${d.reason ? `: ${d.reason}` : ""}`;
      break;
    }
    case "wm":
    case "bb": {
      const store = e.component === "wm" ? "world model" : "blackboard";
      const path = [d.container, d.name].filter(Boolean).join(".");
      if (e.component === "wm" && d.name === "present" && d.value === true) return `${who}: ${d.container} arrives (world model)`;
      if (d.op === "set_property") return `${who}: ${store} ${path} = ${short(value(d.value), 80)}`;
      if (d.op === "remove_property") return `${who}: ${store} ${path} removed`;
      if (d.op === "add_container") return `${who}: ${store} ${d.kind || "container"} ${path} added`;
      if (d.op === "remove_container") return `${who}: ${store} ${path} removed`;
      break;
    }
    case "mind":
      if (e.name === "MindDecision") return `${who}: the mind decides ${d.decision}${d.goal ? ` (${d.goal})` : ""}`;
      if (e.name === "Emotion") return `${who}: mood valence ${d.valence}, arousal ${d.arousal}`;
      if (e.name === "MindAwake") return `${who}: the mind wakes`;
      if (e.name === "MindAsleep") return `${who}: the mind sleeps`;
      break;
    default:
      if (e.name === "Spoke") return `${who} says “${d.text}”`;
      if (e.name === "RemoteAction") return `${who}: ${d.subject ? d.subject + " " : ""}${words(d.name, d.parameters)}`;
  }
  const data = e.data === null || e.data === undefined ? "" : `: ${short(e.data, 120)}`;
  return `${who}: ${e.component} ${e.name}${data}`;
}

function ruleText(rule) {
  if (!rule) return "";
  return rule.startsWith("<built-in>") ? " (built-in rule)" : ` (rule ${rule})`;
}

function eventRow(event) {
  const json = el("details", {}, el("summary", { text: "JSON", "aria-label": `the event's JSON: ${event.component} ${event.name}` }),
    el("pre", { text: JSON.stringify(event, null, 2) }));
  return el("tr", { "data-embodiment": event.embodiment, "data-name": event.name, "data-seq": event.seq },
    el("td", { text: clock(event.time) }), el("td", { text: event.embodiment }),
    el("td", { class: "line", text: eventLine(event) }), el("td", { class: "data" }, json));
}

function addEvent(event) {
  if (event.component === "manager" && event.name === "ActionStarted" && event.data) {
    actionStarts.set(`${event.embodiment}/${event.data.action_id}`, event.time);
    if (actionStarts.size > 500) actionStarts.delete(actionStarts.keys().next().value);
  }
  state.events.push(event);
  drawTimeline();
  if (state.events.length > EVENTS_KEPT) state.events.splice(0, state.events.length - EVENTS_KEPT);
  $("event-count").textContent = `${state.events.length} kept`;
  if ($("filter-pause").checked || !matches(event)) return;
  const body = $("events").tBodies[0];
  body.prepend(eventRow(event));
  while (body.rows.length > EVENT_ROWS) body.lastElementChild.remove();
  stats.drawn.push({ embodiment: event.embodiment, name: event.name, seq: event.seq, time: event.time,
    received: event.received, drawn: now() });
  if (stats.drawn.length > DRAWN_KEPT) stats.drawn.splice(0, stats.drawn.length - DRAWN_KEPT);
}

function redrawEvents() {
  const rows = state.events.filter(matches).slice(-EVENT_ROWS).reverse().map(eventRow);
  $("events").tBodies[0].replaceChildren(...rows);
}

for (const id of ["filter-embodiment", "filter-component", "filter-name", "filter-pause"]) {
  $(id).addEventListener("input", redrawEvents);
}

window.cmionView = { state, stats, send, select, act, migrate, eventLine };
// graph.js (loaded next) draws the graph and the timeline; then the socket opens.
window.addEventListener("DOMContentLoaded", connect);
