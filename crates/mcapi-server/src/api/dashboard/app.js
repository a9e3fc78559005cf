// The mcapi dashboard: the session list (refreshed every 2 s) and a live
// view of one session, fed by its server-sent-events stream
// (GET /v1/sessions/{id}/events). EventSource cannot send an Authorization
// header, so the stream is read with fetch() and parsed here; the API key,
// asked for on a 401, is kept in sessionStorage and never put in a URL.
"use strict";

(() => {
  const KEY_STORE = "mcapi.apiKey";
  const WINDOW = 1000; // ticks kept in the line charts
  const TRAJECTORY = 500; // observations drawn of a continuous world's path
  const FOUND = 400; // stimulus arrivals drawn
  const LIST_EVERY_MS = 2000;
  const RETRY_MS = 2000;
  const PALETTE = ["#2563eb", "#dc2626", "#16a34a", "#9333ea", "#ea580c", "#0891b2", "#ca8a04", "#db2777"];
  // Direction of each grid action on the map: [dx, dy] (rows grow downwards).
  const ARROWS = { left: [-1, 0], right: [1, 0], north: [0, -1], up: [0, -1], south: [0, 1], down: [0, 1] };
  // Viridis, 9 stops.
  const VIRIDIS = ["#440154", "#472d7b", "#3b528b", "#2c728e", "#21918c", "#28ae80", "#5ec962", "#addc30", "#fde725"];

  const $ = (id) => document.getElementById(id);
  const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

  // ------------------------------------------------------------ API key

  let keyDeclined = false;
  let keyPrompt = null;

  function authHeaders(extra) {
    const h = Object.assign({}, extra);
    const key = sessionStorage.getItem(KEY_STORE);
    if (key) h.Authorization = "Bearer " + key;
    return h;
  }

  // Opens the key dialog; resolves true when a key was entered.
  function askKey(message) {
    if (keyPrompt) return keyPrompt;
    keyPrompt = new Promise((resolve) => {
      const dialog = $("key-dialog");
      $("key-message").textContent = message;
      $("key-input").value = "";
      dialog.addEventListener("close", () => {
        keyPrompt = null;
        const key = $("key-input").value.trim();
        if (dialog.returnValue === "ok" && key) {
          sessionStorage.setItem(KEY_STORE, key);
          keyDeclined = false;
          resolve(true);
        } else {
          keyDeclined = true;
          resolve(false);
        }
      }, { once: true });
      dialog.returnValue = "";
      dialog.showModal();
    });
    return keyPrompt;
  }

  // The dialog is asked for automatically once; after a Cancel only the
  // header button opens it.
  async function onUnauthorized(message) {
    // This server has keys: the button to enter one is shown from now on.
    $("key-button").hidden = false;
    const hadKey = sessionStorage.getItem(KEY_STORE) !== null;
    sessionStorage.removeItem(KEY_STORE);
    if (keyDeclined) return false;
    return askKey(hadKey ? "That key was not accepted by this server; enter another." : message);
  }

  async function getJson(path) {
    for (;;) {
      const resp = await fetch(path, { headers: authHeaders({ Accept: "application/json" }), cache: "no-store" });
      if (resp.status === 401) {
        if (await onUnauthorized("This server needs an API key.")) continue;
        throw new Error("an API key is needed");
      }
      const body = await resp.json().catch(() => null);
      if (!resp.ok) throw new Error((body && body.message) || "HTTP " + resp.status);
      return body;
    }
  }

  // ------------------------------------------------------------ helpers

  function ago(ms) {
    const s = Math.round(ms / 1000);
    if (s < 2) return "just now";
    if (s < 90) return s + " s ago";
    if (s < 5400) return Math.round(s / 60) + " min ago";
    return Math.round(s / 3600) + " h ago";
  }

  function describeModel(m) {
    const parts = [];
    if (m.layout) parts.push("grid " + m.layout.rows + "×" + m.layout.cols);
    if (m.continuous) parts.push("continuous, d = " + m.continuous.observation_space.low.length);
    else parts.push(m.states + " states");
    parts.push(m.actions.length + " actions");
    parts.push("stimuli " + m.stimuli.join(", "));
    parts.push(m.basis.kind === "indicator" ? "indicator basis" : m.basis.kind + " basis (k = " + m.basis.k + ")");
    return parts.join(" · ");
  }

  function colour(t) {
    const x = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
    const i = Math.min(VIRIDIS.length - 2, Math.floor(x));
    const f = x - i;
    const a = VIRIDIS[i], b = VIRIDIS[i + 1];
    const ch = (c, k) => parseInt(c.slice(1 + 2 * k, 3 + 2 * k), 16);
    const mix = (k) => Math.round(ch(a, k) + (ch(b, k) - ch(a, k)) * f);
    return "rgb(" + mix(0) + "," + mix(1) + "," + mix(2) + ")";
  }

  function fmt(v) {
    if (v === null || v === undefined || !Number.isFinite(v)) return "–";
    const a = Math.abs(v);
    if (a !== 0 && (a < 0.01 || a >= 1e5)) return v.toExponential(2);
    return v.toFixed(a < 10 ? 3 : 1);
  }

  // ------------------------------------------------------------ session list

  const known = new Map(); // id -> { model }
  let selectedId = null;
  // Until the user picks a session (or one is named in the URL), the page
  // follows the most recently active one.
  let picked = false;

  async function refreshList() {
    let page;
    try {
      page = await getJson("/v1/sessions?limit=100");
    } catch (e) {
      $("sessions-note").textContent = "cannot list sessions: " + e.message;
      return;
    }
    const ids = new Set();
    for (const s of page.sessions) {
      ids.add(s.id);
      if (!known.has(s.id)) {
        const k = { model: null };
        known.set(s.id, k);
        getJson("/v1/sessions/" + encodeURIComponent(s.id))
          .then((info) => { k.model = info.model; renderList(page); })
          .catch(() => {});
      }
    }
    for (const id of known.keys()) if (!ids.has(id)) known.delete(id);
    $("sessions-note").textContent = page.next
      ? "the first " + page.sessions.length + " sessions"
      : page.sessions.length + (page.sessions.length === 1 ? " session" : " sessions");
    renderList(page);
    if (!picked && page.sessions.length) {
      const idle = (s) => (s.idle_ms == null ? Infinity : s.idle_ms);
      const recent = page.sessions.reduce((a, b) => (idle(b) < idle(a) ? b : a));
      if (recent.id !== selectedId) select(recent.id);
    }
  }

  function renderList(page) {
    const body = $("sessions").tBodies[0];
    const rows = page.sessions.map((s) => {
      const k = known.get(s.id) || {};
      const tr = document.createElement("tr");
      tr.dataset.id = s.id;
      if (s.id === selectedId) tr.className = "selected";
      const cells = [
        [s.id, "id"],
        [k.model ? describeModel(k.model) : s.states + " states", ""],
        [String(s.tick), "num"],
        [s.update_mode, ""],
        [s.idle_ms == null ? "none since start" : ago(s.idle_ms), ""],
      ];
      for (const [text, cls] of cells) {
        const td = document.createElement("td");
        td.textContent = text;
        if (cls) td.className = cls;
        tr.appendChild(td);
      }
      tr.lastChild.title = "the session's last observation (the server's clock)";
      tr.addEventListener("click", () => { picked = true; select(s.id); });
      return tr;
    });
    body.replaceChildren(...rows);
    $("sessions-empty").hidden = page.sessions.length > 0;
    $("empty-create").textContent = "curl -s -X POST " + location.origin +
      "/v1/sessions -H 'content-type: application/json' -d '{\"model\": {\"preset\": \"hallway\"}}'";
  }

  async function listLoop() {
    for (;;) {
      await refreshList();
      await sleep(LIST_EVERY_MS);
    }
  }

  // ------------------------------------------------------------ SSE

  // Reads a text/event-stream body; calls onEvent(type, data) per event.
  // Resolves true when onEvent returned "stop", false when the body ended.
  async function readEvents(body, onEvent) {
    const reader = body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return false;
      buf += value.replace(/\r\n?/g, "\n");
      let cut;
      while ((cut = buf.indexOf("\n\n")) >= 0) {
        const block = buf.slice(0, cut);
        buf = buf.slice(cut + 2);
        let type = "message";
        const data = [];
        for (const line of block.split("\n")) {
          if (line === "" || line.startsWith(":")) continue;
          const colon = line.indexOf(":");
          const field = colon < 0 ? line : line.slice(0, colon);
          let v = colon < 0 ? "" : line.slice(colon + 1);
          if (v.startsWith(" ")) v = v.slice(1);
          if (field === "event") type = v;
          else if (field === "data") data.push(v);
        }
        if (data.length === 0) continue;
        let parsed;
        try {
          parsed = JSON.parse(data.join("\n"));
        } catch (e) {
          continue;
        }
        if (onEvent(type, parsed) === "stop") {
          reader.cancel().catch(() => {});
          return true;
        }
      }
    }
  }

  function setStream(view, text, cls) {
    if (view !== current) return;
    const dd = $("fact-stream");
    dd.textContent = text;
    dd.className = cls ? "state-" + cls : "";
    const pill = $("conn");
    pill.hidden = false;
    pill.textContent = text;
    pill.className = "pill " + (cls || "");
  }

  async function streamLoop(view) {
    const url = "/v1/sessions/" + encodeURIComponent(view.id) + "/events?interval_ms=250";
    while (!view.closed) {
      try {
        const resp = await fetch(url, {
          headers: authHeaders({ Accept: "text/event-stream" }),
          signal: view.abort.signal,
          cache: "no-store",
        });
        if (resp.status === 401) {
          setStream(view, "API key needed", "bad");
          if (await onUnauthorized("This server needs an API key to stream this session.")) continue;
          return;
        }
        if (resp.status === 404) {
          setStream(view, "session not found", "bad");
          return;
        }
        if (!resp.ok) throw new Error("HTTP " + resp.status);
        setStream(view, "live", "ok");
        if (await readEvents(resp.body, (type, data) => onEvent(view, type, data))) return;
      } catch (e) {
        if (view.closed) return;
      }
      setStream(view, "reconnecting", "warn");
      await sleep(RETRY_MS);
    }
  }

  // ------------------------------------------------------------ session view

  let current = null;

  // Stops the stream of the current view and frees its charts.
  function closeView() {
    if (!current) return;
    current.closed = true;
    current.abort.abort();
    for (const o of current.observers) o.disconnect();
    for (const c of Object.values(current.charts)) c.destroy();
    current = null;
  }

  function select(id) {
    if (current && current.id === id) return;
    closeView();
    selectedId = id;
    for (const tr of $("sessions").tBodies[0].rows) tr.classList.toggle("selected", tr.dataset.id === id);
    if (location.hash !== "#" + id) history.replaceState(null, "", "#" + id);
    current = {
      id,
      closed: false,
      abort: new AbortController(),
      info: null,
      charts: {},
      observers: [],
      x: [],
      drive: [],
      cum: [],
      totals: [],
      reward: [],
      err: [],
      xiCur: [],
      eps: [],
      modules: null,
      lastTick: null,
      state: null,
      traj: [],
      found: [],
      sawStimulus: false,
      values: null,
      dirty: false,
    };
    $("view").hidden = false;
    $("view-title").textContent = id;
    $("view-model").textContent = "";
    for (const f of ["tick", "state", "drive", "policy"]) $("fact-" + f).textContent = "–";
    for (const el of ["chart-drive", "chart-stimulus", "chart-reward", "chart-values", "chart-curiosity"]) $(el).replaceChildren();
    $("curiosity-card").hidden = true;
    streamLoop(current);
  }

  function onEvent(view, type, data) {
    if (view.closed) return "stop";
    switch (type) {
      case "session":
        if (!view.info) {
          view.info = data;
          setup(view);
        }
        break;
      case "tick":
        addTick(view, data);
        break;
      case "values":
        view.values = data;
        break;
      case "end":
        setStream(view, "ended: session deleted", "bad");
        view.closed = true;
        return "stop";
      case "error":
        setStream(view, "error: " + (data.message || data.code), "bad");
        break;
      default:
        return undefined;
    }
    schedule(view);
    return undefined;
  }

  function addTick(view, e) {
    if (view.lastTick !== null && e.tick <= view.lastTick) return; // resent after a reconnect
    view.lastTick = e.tick;
    view.state = e.state;
    if (Array.isArray(e.observation)) {
      // A continuous world: the trajectory, and where a stimulus came.
      view.state = e.observation;
      view.traj.push(e.observation);
      if (view.traj.length > TRAJECTORY) view.traj.splice(0, view.traj.length - TRAJECTORY);
      (e.stimulus || []).forEach((x, d) => {
        if (Number(x) > 0) view.found.push({ at: e.observation, dim: d });
      });
      if (view.found.length > FOUND) view.found.splice(0, view.found.length - FOUND);
    }
    view.x.push(e.tick);
    const n = view.info ? view.info.model.stimuli.length : e.drive.length;
    for (let d = 0; d < n; d++) view.drive[d].push(e.drive[d] ?? null);
    if (Array.isArray(e.stimulus)) {
      view.sawStimulus = true;
      for (let d = 0; d < n; d++) view.totals[d] += Number(e.stimulus[d]) || 0;
    }
    for (let d = 0; d < n; d++) view.cum[d].push(view.sawStimulus ? view.totals[d] : null);
    view.reward.push(e.reward);
    view.err.push(e.lstdq_error);
    const c = e.curiosity;
    view.xiCur.push(c ? c.xi_cur : null);
    view.eps.push(c ? c.epsilon : null);
    if (c) view.modules = c.modules;
    if (view.x.length > WINDOW) {
      const k = view.x.length - WINDOW;
      for (const a of [view.x, view.reward, view.err, view.xiCur, view.eps, ...view.drive, ...view.cum]) a.splice(0, k);
    }
  }

  function lineChart(view, el, series, extra) {
    const opts = Object.assign({
      width: Math.max(300, el.clientWidth),
      height: 250,
      scales: { x: { time: false } },
      axes: [{ label: "tick" }, {}],
      series: [{ label: "tick" }].concat(series),
      legend: { live: true },
    }, extra || {});
    const chart = new uPlot(opts, [[], ...series.map(() => [])], el);
    const observer = new ResizeObserver(() => {
      const w = Math.max(300, el.clientWidth);
      if (w !== chart.width) chart.setSize({ width: w, height: 250 });
    });
    observer.observe(el);
    view.observers.push(observer);
    return chart;
  }

  function setup(view) {
    const m = view.info.model;
    $("view-model").textContent = describeModel(m) + " · " + view.info.agent.update_mode;
    const names = m.stimuli;
    view.drive = names.map(() => []);
    view.cum = names.map(() => []);
    view.totals = names.map(() => 0);
    const line = (label, i) => ({ label, stroke: PALETTE[i % PALETTE.length], width: 1.6 });
    view.charts.drive = lineChart(view, $("chart-drive"), names.map(line), {
      scales: { x: { time: false }, y: { range: [-1, 1] } },
    });
    view.charts.stimulus = lineChart(view, $("chart-stimulus"), names.map(line));
    view.charts.reward = lineChart(view, $("chart-reward"), [
      { label: "|r|", stroke: "#2563eb", width: 1.4 },
      { label: "LSTDQ error", stroke: "#dc2626", width: 1.4, scale: "err" },
    ], {
      scales: { x: { time: false } },
      axes: [{ label: "tick" }, { label: "|r|" }, { scale: "err", side: 1, label: "LSTDQ error", grid: { show: false } }],
    });
    // A session with a curiosity channel (docs/algorithm.md §7): ξ_cur and ε.
    const curious = !!view.info.curiosity;
    $("curiosity-card").hidden = !curious;
    if (curious) {
      view.modules = view.info.curiosity.modules.length;
      view.charts.curiosity = lineChart(view, $("chart-curiosity"), [
        { label: "ξ_cur", stroke: "#16a34a", width: 1.4 },
        { label: "ε", stroke: "#9333ea", width: 1.4, scale: "eps" },
      ], {
        scales: { x: { time: false } },
        axes: [{ label: "tick" }, { label: "ξ_cur" }, { scale: "eps", side: 1, label: "ε", grid: { show: false } }],
      });
    }
    const grid = !!m.layout || !!m.continuous;
    $("heatmap").hidden = !grid;
    $("chart-values").hidden = grid;
    const dim = m.continuous ? m.continuous.observation_space.low.length : 0;
    $("values-caption").textContent = m.continuous
      ? (dim <= 2
        ? "V over the observation space, the recent path, where stimuli came (dots by stimulus) and the agent (red ring)"
        : "The first two of " + dim + " coordinates: V at recent observations, where stimuli came and the agent (red ring)")
      : grid
        ? "V over the map, greedy policy (arrows; dots stay) and the agent (red ring)"
        : "V per state (bars) and the agent (red dot)";
    if (!grid) {
      view.charts.values = lineChart(view, $("chart-values"), [
        { label: "V", stroke: "#2563eb", fill: "rgba(37,99,235,0.35)", paths: uPlot.paths.bars({ size: [0.8, 24] }) },
        { label: "agent", stroke: "#dc2626", paths: () => null, points: { show: true, size: 10, fill: "#dc2626" } },
      ], { axes: [{ label: "state" }, { label: "V" }], scales: { x: { time: false } } });
    }
  }

  function schedule(view) {
    if (view.dirty) return;
    view.dirty = true;
    requestAnimationFrame(() => {
      view.dirty = false;
      if (!view.closed || view === current) draw(view);
    });
  }

  function draw(view) {
    if (!view.info) return;
    const names = view.info.model.stimuli;
    $("fact-tick").textContent = view.lastTick === null ? String(view.info.tick) : String(view.lastTick);
    $("fact-state").textContent = view.state === null ? "–"
      : Array.isArray(view.state) ? "(" + view.state.map(fmt).join(", ") + ")" : String(view.state);
    const last = view.drive.map((d) => d[d.length - 1]);
    if (last.length && last[0] !== undefined) {
      let best = 0;
      for (let d = 1; d < last.length; d++) if (Math.abs(last[d]) > Math.abs(last[best])) best = d;
      $("fact-drive").textContent = names[best];
    }
    if (view.values) $("fact-policy").textContent = String(view.values.policy_version);
    view.charts.drive.setData([view.x, ...view.drive]);
    view.charts.stimulus.setData([view.x, ...view.cum]);
    view.charts.reward.setData([view.x, view.reward, view.err]);
    if (view.charts.curiosity) {
      view.charts.curiosity.setData([view.x, view.xiCur, view.eps]);
      $("curiosity-modules").textContent = String(view.modules ?? 0);
      $("chart-curiosity").dataset.points = String(view.xiCur.filter((x) => x !== null).length);
    }
    $("stimulus-missing").hidden = view.sawStimulus || view.x.length === 0;
    $("chart-stimulus").dataset.total = String(view.totals.reduce((a, b) => a + b, 0));
    for (const id of ["chart-drive", "chart-stimulus", "chart-reward"]) {
      $(id).dataset.points = String(view.x.length);
      $(id).dataset.lastTick = view.x.length ? String(view.x[view.x.length - 1]) : "";
    }
    if (view.values && view.values.v) {
      if (view.info.model.continuous) drawContinuous(view);
      else if (view.info.model.layout) drawHeatmap(view);
      else drawBars(view);
    }
  }

  function drawBars(view) {
    const v = view.values.v;
    const xs = v.map((_, s) => s);
    const agent = v.map((val, s) => (s === view.state ? val : null));
    view.charts.values.setData([xs, v, agent]);
    $("chart-values").dataset.version = String(view.values.policy_version);
  }

  // The colour scale of V under a heatmap, from lo to hi.
  function colourBar(ctx, y0, w, lo, hi) {
    const barW = Math.min(w, 320);
    for (let i = 0; i < barW; i++) {
      ctx.fillStyle = colour(i / (barW - 1));
      ctx.fillRect(i, y0, 1, 10);
    }
    ctx.fillStyle = "#1c2430";
    ctx.font = "12px system-ui, sans-serif";
    ctx.textBaseline = "top";
    ctx.textAlign = "left";
    ctx.fillText("V " + fmt(lo), 0, y0 + 12);
    ctx.textAlign = "right";
    ctx.fillText(fmt(hi), barW, y0 + 12);
  }

  function drawHeatmap(view) {
    const canvas = $("heatmap");
    const { rows, cols, cells, marks } = view.info.model.layout;
    const v = view.values.v;
    const policy = view.values.policy || [];
    const width = Math.max(300, $("heatmap-box").clientWidth);
    const cell = Math.max(4, Math.min(Math.floor(width / cols), Math.floor(420 / rows)));
    const barH = 26;
    const w = cell * cols, h = cell * rows + barH + 8;
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
      canvas.style.width = w + "px";
      canvas.style.height = h + "px";
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    ctx.fillStyle = "#2b3440"; // walls
    ctx.fillRect(0, 0, w, cell * rows);
    const finite = v.filter(Number.isFinite);
    const lo = finite.length ? Math.min(...finite) : 0;
    const hi = finite.length ? Math.max(...finite) : 1;
    const span = hi - lo || 1;
    const n = Math.min(cells.length, v.length);
    for (let s = 0; s < n; s++) {
      const [r, c] = cells[s];
      ctx.fillStyle = Number.isFinite(v[s]) ? colour((v[s] - lo) / span) : "#999";
      ctx.fillRect(c * cell, r * cell, cell, cell);
    }
    // Policy: an arrow per state, a dot for stay.
    ctx.strokeStyle = "rgba(255,255,255,0.85)";
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.lineWidth = Math.max(1, cell / 12);
    for (let s = 0; s < Math.min(n, policy.length); s++) {
      const [r, c] = cells[s];
      const cx = c * cell + cell / 2, cy = r * cell + cell / 2;
      const dir = ARROWS[policy[s]];
      if (!dir) {
        ctx.beginPath();
        ctx.arc(cx, cy, Math.max(1, cell / 10), 0, 2 * Math.PI);
        ctx.fill();
        continue;
      }
      const len = cell * 0.34, head = cell * 0.16;
      const tx = cx + dir[0] * len, ty = cy + dir[1] * len;
      ctx.beginPath();
      ctx.moveTo(cx - dir[0] * len, cy - dir[1] * len);
      ctx.lineTo(tx, ty);
      ctx.moveTo(tx - dir[0] * head - dir[1] * head, ty - dir[1] * head - dir[0] * head);
      ctx.lineTo(tx, ty);
      ctx.lineTo(tx - dir[0] * head + dir[1] * head, ty - dir[1] * head + dir[0] * head);
      ctx.stroke();
    }
    // Sources: their marks.
    ctx.font = "bold " + Math.max(9, Math.round(cell * 0.7)) + "px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    for (const { mark, state } of marks || []) {
      if (state >= n) continue;
      const [r, c] = cells[state];
      ctx.fillStyle = "#ffffff";
      ctx.strokeStyle = "#111827";
      ctx.lineWidth = 3;
      ctx.strokeText(mark, c * cell + cell / 2, r * cell + cell / 2);
      ctx.fillText(mark, c * cell + cell / 2, r * cell + cell / 2);
    }
    // The agent.
    if (view.state !== null && view.state < n) {
      const [r, c] = cells[view.state];
      ctx.strokeStyle = "#ef4444";
      ctx.lineWidth = Math.max(2, cell / 7);
      ctx.beginPath();
      ctx.arc(c * cell + cell / 2, r * cell + cell / 2, cell * 0.42, 0, 2 * Math.PI);
      ctx.stroke();
    }
    // Colour bar.
    const y0 = cell * rows + 8;
    colourBar(ctx, y0, w, lo, hi);
    canvas.dataset.version = String(view.values.policy_version);
    canvas.dataset.draws = String(Number(canvas.dataset.draws || 0) + 1);
    canvas.dataset.state = view.state === null ? "" : String(view.state);
  }

  /**
   * A continuous world on the heatmap canvas. d = 1 and d = 2: V on the
   * server's grid of points (a strip for d = 1); above, the first two
   * coordinates, V as dots at the recent observations the server evaluated.
   * Over it the recent path, a dot per stimulus arrival (the stimulus's
   * colour) and the agent.
   */
  function drawContinuous(view) {
    const canvas = $("heatmap");
    const space = view.info.model.continuous.observation_space;
    const d = space.low.length;
    const points = view.values.points || [];
    const v = view.values.v;
    const width = Math.min(Math.max(300, $("heatmap-box").clientWidth), 560);
    const plotH = d === 1 ? 60 : width;
    const barH = 26;
    const w = width, h = plotH + barH + 8;
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
      canvas.style.width = w + "px";
      canvas.style.height = h + "px";
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    ctx.fillStyle = "#2b3440";
    ctx.fillRect(0, 0, w, plotH);
    // Screen position of an observation (y grows upwards).
    const px = (x) => ((x[0] - space.low[0]) / (space.high[0] - space.low[0])) * w;
    const py = (x) => d === 1 ? plotH / 2 : plotH - ((x[1] - space.low[1]) / (space.high[1] - space.low[1])) * plotH;
    const finite = v.filter(Number.isFinite);
    const lo = finite.length ? Math.min(...finite) : 0;
    const hi = finite.length ? Math.max(...finite) : 1;
    const span = hi - lo || 1;
    const n = Math.min(points.length, v.length);
    if (d <= 2) {
      // The grid: cells centred on its points.
      const side = d === 1 ? n : Math.round(Math.sqrt(n));
      const cw = w / Math.max(1, side - 1), ch = d === 1 ? plotH : plotH / Math.max(1, side - 1);
      for (let i = 0; i < n; i++) {
        ctx.fillStyle = Number.isFinite(v[i]) ? colour((v[i] - lo) / span) : "#999";
        ctx.fillRect(px(points[i]) - cw / 2, py(points[i]) - ch / 2, cw + 1, ch + 1);
      }
    } else {
      for (let i = 0; i < n; i++) {
        ctx.fillStyle = Number.isFinite(v[i]) ? colour((v[i] - lo) / span) : "#999";
        ctx.beginPath();
        ctx.arc(px(points[i]), py(points[i]), 4, 0, 2 * Math.PI);
        ctx.fill();
      }
    }
    // The recent path.
    if (view.traj.length > 1) {
      ctx.strokeStyle = "rgba(255,255,255,0.55)";
      ctx.lineWidth = 1;
      ctx.beginPath();
      ctx.moveTo(px(view.traj[0]), py(view.traj[0]));
      for (const x of view.traj.slice(1)) ctx.lineTo(px(x), py(x));
      ctx.stroke();
    }
    // Where stimuli came: the sources found.
    for (const { at, dim } of view.found) {
      ctx.fillStyle = PALETTE[dim % PALETTE.length];
      ctx.strokeStyle = "#ffffff";
      ctx.lineWidth = 1;
      ctx.beginPath();
      ctx.arc(px(at), py(at), 3.5, 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
    }
    // The agent.
    if (Array.isArray(view.state)) {
      ctx.strokeStyle = "#ef4444";
      ctx.lineWidth = 3;
      ctx.beginPath();
      ctx.arc(px(view.state), py(view.state), 8, 0, 2 * Math.PI);
      ctx.stroke();
    }
    // Colour bar.
    const y0 = plotH + 8;
    colourBar(ctx, y0, w, lo, hi);
    canvas.dataset.version = String(view.values.policy_version);
    canvas.dataset.draws = String(Number(canvas.dataset.draws || 0) + 1);
    canvas.dataset.found = String(view.found.length);
    canvas.dataset.path = String(view.traj.length);
  }

  // ------------------------------------------------------------ start

  document.addEventListener("DOMContentLoaded", () => {
    $("key-button").addEventListener("click", async () => {
      keyDeclined = false;
      if (await askKey("Enter an API key of this server.")) {
        refreshList();
        if (current) {
          const id = current.id;
          closeView();
          select(id);
        }
      }
    });
    listLoop();
    const hash = decodeURIComponent(location.hash.slice(1));
    if (hash) {
      picked = true;
      select(hash);
    }
  });
})();
