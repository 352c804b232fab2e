// The editor page: shows the frames the server renders and sends what the user changes.
"use strict";

const $ = (id) => document.getElementById(id);
let state = null;
// The server's per-session token, written into this page: every POST carries it.
const TOKEN = document.querySelector('meta[name="vqm-token"]').content;
// Answers that can change the selected material's values: the panel then shows them.
const PANEL_ACTIONS = new Set(["select", "edit", "undo", "redo"]);

function showMessage(text, error) {
  const m = $("message");
  m.textContent = text || "";
  m.className = error ? "error" : "";
}

async function post(action, body) {
  const r = await fetch("/api/" + action, {
    method: "POST", headers: { "Content-Type": "application/json", "X-VQM-Token": TOKEN },
    body: JSON.stringify(body || {}),
  });
  const data = await r.json();
  if (!r.ok) { showMessage(data.error, true); return null; }
  if (data.state) applyState(data.state);
  // a slider being dragged keeps its own value (answers to earlier drag steps come in late)
  if (data.state && PANEL_ACTIONS.has(action) && !(body && body.live)) showSelectedMaterial();
  return data;
}

// One request in flight per channel; while it runs only the newest value waits (drags stay smooth
// and a slider's final value always arrives after its live ones).
const channels = {};
function sendLatest(channel, action, body) {
  const c = channels[channel] || (channels[channel] = { busy: false, next: null });
  c.next = { action, body };
  if (c.busy) return;
  (async () => {
    c.busy = true;
    while (c.next) { const n = c.next; c.next = null; await post(n.action, n.body); }
    c.busy = false;
  })();
}

function fillSelect(sel, values, current, label) {
  const keep = sel.dataset.filled === "1";
  if (!keep) {
    for (const v of values) {
      const o = document.createElement("option");
      o.value = v.value ?? v; o.textContent = label ? label(v) : (v.value ?? v);
      sel.appendChild(o);
    }
    sel.dataset.filled = "1";
  }
  if (current !== undefined) sel.value = current;
}

function applyState(s) {
  state = s;
  $("run").textContent = s.run;
  const views = s.views.map((v) => ({ value: v.name, split: v.split }));
  if (s.view === "orbit" && !$("view").querySelector('option[value="orbit"]')) {
    const o = document.createElement("option"); o.value = "orbit"; o.textContent = "free orbit";
    $("view").appendChild(o);
  }
  fillSelect($("view"), views, s.view, (v) => `${v.value} (${v.split})`);
  fillSelect($("mode"), s.modes, s.mode);
  fillSelect($("envmap"), s.envmaps, s.lighting.envmap);
  $("lamps").hidden = !s.lamps;
  $("lamps").textContent = s.lamps ? `+ ${s.lamps} fitted lamp${s.lamps > 1 ? "s" : ""} with the fitted envmap` : "";
  fillSelect($("preset"), s.presets);
  buildInputs(s.inputs);
  const ul = $("materials");
  if (!ul.dataset.filled) {
    for (const m of s.materials) {
      const li = document.createElement("li");
      li.dataset.id = m.id;
      li.innerHTML = `<span style="background:${m.colour}"></span>${m.id}`;
      li.title = `material ${m.id}`;
      li.addEventListener("click", (ev) => selectMaterials(ev.shiftKey ? [...s.selection.materials, m.id] : [m.id]));
      ul.appendChild(li);
    }
    ul.dataset.filled = "1";
    if (!s.materials.length) ul.textContent = "no discrete branch: select with a box";
  }
  for (const li of ul.children) li.classList.toggle("on", s.selection.materials.includes(+li.dataset.id));
  const sel = s.selection.materials;
  $("selected").textContent = sel.length ? `selected: material ${sel.join(", ")}` +
    (s.selection.boxes.length ? " inside the box" : "") : (s.selection.boxes.length ? "selected: the box" : "nothing selected");
  $("frame").dataset.selected = sel.join(",");
  const boxIn = [0, 1, 2, 3, 4, 5].map((i) => $("b" + i));
  if (boxIn[0].value === "") s.bounds.flat().forEach((v, i) => { boxIn[i].value = v.toFixed(3); });
  const ol = $("edits");
  ol.innerHTML = "";
  for (const e of s.edits) { const li = document.createElement("li"); li.textContent = e; ol.appendChild(li); }
  $("undo").disabled = !s.can_undo;
  $("redo").disabled = !s.can_redo;
  if (!$("save-name").value) $("save-name").value = s.save_name;
  if (s.job && s.job.state === "running") showMessage(s.message);
}

// One control per BRDF input, as the server declares them (state.inputs), its id the input's name:
// a colour picker for a colour, a slider and its value (id NAME-out) for a scalar.
function buildInputs(inputs) {
  const box = $("inputs");
  if (box.dataset.filled) return;
  for (const inp of inputs) {
    const label = document.createElement("label");
    const el = document.createElement("input");
    el.id = inp.name;
    label.append(inp.name[0].toUpperCase() + inp.name.slice(1) + " ", el);
    if (inp.channels === 3) {
      el.type = "color";
      el.value = "#808080";
    } else {
      Object.assign(el, { type: "range", min: inp.low, max: inp.high, step: inp.step });
      el.value = inp.default ?? inp.low;
      const out = document.createElement("output");
      out.id = inp.name + "-out";
      out.textContent = el.value;
      label.append(" ", out);
    }
    box.appendChild(label);
  }
  box.dataset.filled = "1";
}

function currentBox() {
  if (!$("use-box").checked) return null;
  const v = [0, 1, 2, 3, 4, 5].map((i) => parseFloat($("b" + i).value));
  return [v.slice(0, 3), v.slice(3)];
}

async function selectMaterials(ids) {
  const r = await post("select", { materials: ids, box: currentBox() });
  if (r) showMessage("");
}

// The panel shows the last selected material's values as the edits so far leave them.
function showSelectedMaterial() {
  const ids = state ? state.selection.materials : [];
  if (ids.length) setControlsFromMaterial(ids[ids.length - 1]);
}

function setControlsFromMaterial(id) {
  const m = state && state.materials.find((x) => x.id === id);
  if (!m || state.inputs.some((inp) => m[inp.name] == null)) return;
  for (const inp of state.inputs) {
    const k = inp.name;
    if (inp.channels === 3) {
      const srgb = m[k].map((c) => (c <= 0.0031308 ? 12.92 * c : 1.055 * Math.pow(c, 1 / 2.4) - 0.055));
      $(k).value = "#" + srgb.map((c) => Math.round(Math.min(1, Math.max(0, c)) * 255).toString(16).padStart(2, "0")).join("");
    } else {
      $(k).value = m[k];
      $(k + "-out").textContent = (+m[k]).toFixed(2);
    }
  }
}

// --- frames: long-poll for the newest one --------------------------------------------------------
async function frames() {
  let version = -1, spp = -1;
  const img = $("frame");
  for (;;) {
    try {
      const r = await fetch(`/api/frame?version=${version}&spp=${spp}`);
      if (r.status !== 200) { await new Promise((ok) => setTimeout(ok, 500)); continue; }
      version = +r.headers.get("X-Frame-Version");
      spp = +r.headers.get("X-Frame-Spp");
      const seconds = +r.headers.get("X-Frame-Seconds");
      const url = URL.createObjectURL(await r.blob());
      await new Promise((ok) => { img.onload = ok; img.onerror = ok; img.src = url; });
      if (img.dataset.url) URL.revokeObjectURL(img.dataset.url);
      img.dataset.url = url;
      const scale = Math.max(1, Math.floor(512 / Math.max(img.naturalWidth, img.naturalHeight)));
      img.width = img.naturalWidth * scale;
      img.height = img.naturalHeight * scale;
      img.dataset.version = version;
      img.dataset.spp = spp;
      const refined = state && spp >= state.refine_spp;
      $("status").textContent = `${spp < 8 ? "preview" : refined ? "refined" : "refining"}: ${spp} spp, ` +
        `${seconds.toFixed(2)} s after the change`;
    } catch (e) {
      $("status").textContent = "lost the server; retrying";
      await new Promise((ok) => setTimeout(ok, 1000));
    }
  }
}

// --- the view: click selects, drag orbits, wheel zooms ---------------------------------------------
function framePixel(ev) {
  const img = $("frame");
  const r = img.getBoundingClientRect();
  return [Math.floor((ev.clientX - r.left) * img.naturalWidth / r.width),
          Math.floor((ev.clientY - r.top) * img.naturalHeight / r.height)];
}

function setupView() {
  const img = $("frame");
  let down = null;
  img.addEventListener("mousedown", (ev) => { down = { x: ev.clientX, y: ev.clientY, lx: ev.clientX, ly: ev.clientY, moved: false }; });
  window.addEventListener("mousemove", (ev) => {
    if (!down) return;
    const dx = ev.clientX - down.lx, dy = ev.clientY - down.ly;
    if (Math.abs(ev.clientX - down.x) + Math.abs(ev.clientY - down.y) > 3) down.moved = true;
    if (!down.moved || (dx === 0 && dy === 0)) return;
    down.lx = ev.clientX; down.ly = ev.clientY;
    const c = channels.orbit;
    const pending = c && c.next ? c.next.body : { yaw: 0, pitch: 0 };
    sendLatest("orbit", "orbit", { yaw: pending.yaw - dx * 0.4, pitch: pending.pitch + dy * 0.4 });
  });
  window.addEventListener("mouseup", async (ev) => {
    if (!down) return;
    const wasClick = !down.moved;
    down = null;
    if (!wasClick || ev.target !== img) return;
    const [x, y] = framePixel(ev);
    const r = await post("select", { pixel: [x, y], add: ev.shiftKey, box: currentBox() });
    if (r) showMessage("");
  });
  img.addEventListener("wheel", (ev) => {
    ev.preventDefault();
    sendLatest("orbit", "orbit", { zoom: ev.deltaY > 0 ? 1.1 : 1 / 1.1 });
  }, { passive: false });
}

// --- controls ----------------------------------------------------------------------------------
function setupControls() {
  $("view").addEventListener("change", () => { if ($("view").value !== "orbit") post("view", { name: $("view").value }); });
  $("mode").addEventListener("change", () => post("mode", { mode: $("mode").value }));
  const lighting = () => {
    $("rotate-out").textContent = `${$("rotate").value}\u00b0`;
    $("exposure-out").textContent = `${(+$("exposure").value).toFixed(1)} EV`;
    sendLatest("lighting", "lighting", { envmap: $("envmap").value, rotate: +$("rotate").value, exposure: +$("exposure").value });
  };
  for (const id of ["envmap", "rotate", "exposure"]) $(id).addEventListener(id === "envmap" ? "change" : "input", lighting);

  const change = (inp, live) => {
    const key = inp.name;
    const value = inp.channels === 3 ? $(key).value : +$(key).value;
    if (inp.channels !== 3) $(key + "-out").textContent = value.toFixed(2);
    sendLatest("edit", "edit", { changes: [{ op: "set", key, value }], live });
  };
  for (const inp of state.inputs) {
    $(inp.name).addEventListener("input", () => change(inp, true));
    $(inp.name).addEventListener("change", () => change(inp, false));
  }
  $("preset").addEventListener("change", () => {
    if ($("preset").value) sendLatest("edit", "edit", { preset: $("preset").value });
    $("preset").value = "";
  });
  const box = () => post("select", { materials: state ? state.selection.materials : [], box: currentBox() });
  $("use-box").addEventListener("change", box);
  for (let i = 0; i < 6; i++) $("b" + i).addEventListener("change", () => { if ($("use-box").checked) box(); });
  $("undo").addEventListener("click", () => post("undo"));
  $("redo").addEventListener("click", () => post("redo"));
  document.addEventListener("keydown", (ev) => {
    if (!(ev.ctrlKey || ev.metaKey) || ev.target.tagName === "INPUT") return;
    if (ev.key === "z" && !ev.shiftKey) { ev.preventDefault(); post("undo"); }
    if (ev.key === "y" || (ev.key === "Z" && ev.shiftKey)) { ev.preventDefault(); post("redo"); }
  });
  $("save").addEventListener("click", async () => {
    const r = await post("save", { name: $("save-name").value });
    if (r) showMessage(`saved ${r.path}`);
  });
  $("export").addEventListener("click", async () => {
    const r = await post("export", { name: $("save-name").value, format: $("format").value });
    if (r) pollJob();
  });
}

async function pollJob() {
  for (;;) {
    const s = await (await fetch("/api/state")).json();
    applyState(s);
    if (!s.job || s.job.state !== "running") { showMessage(s.message, s.job && s.job.state === "failed"); return; }
    await new Promise((ok) => setTimeout(ok, 1000));
  }
}

(async () => {
  applyState(await (await fetch("/api/state")).json());
  setupView();
  setupControls();
  frames();
})();
