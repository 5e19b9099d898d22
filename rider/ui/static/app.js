// Operator page: live machine view over server-sent events, commands over POST.
// No framework, no build step: the page must work on a machine with no internet.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const SVG = "http://www.w3.org/2000/svg";

  const ui = {
    cfg: null,
    status: null,
    io: new Map(),
    diag: null,
    calibration: null,
    link: { up: false, reason: "connecting to the machine…", machine: null },
    server: { up: false, reason: "connecting to the UI server…", lastMsg: 0, time: 0, at: 0 },
    history: [],
    sample: null,
    busy: new Set(),
    awaiting: new Map(), // transaction_id → label of a motion this page started
    notices: new Map(), // transaction_id → completion notice seen (a notice may beat its reply)
    es: null,
    retry: null,
    uploaded: [],
  };

  const lostAfterMs = () => (ui.cfg ? ui.cfg.lost_after_s : 1.5) * 1000;
  const live = () => ui.server.up && ui.link.up && ui.status !== null;
  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

  // ------------------------------------------------------------------------- start-up
  async function fetchConfig() {
    try {
      const r = await fetch("/api/config", { cache: "no-store" });
      return r.ok ? await r.json() : null;
    } catch (err) {
      return null; // the server is not up (yet): the caller retries
    }
  }

  function applyConfig(cfg) {
    ui.cfg = cfg;
    buildCommands();
    buildSessions();
  }

  async function boot() {
    let cfg;
    while (!(cfg = await fetchConfig())) {
      setServer(false, "the UI server is not answering; retrying…");
      await sleep(1000);
    }
    applyConfig(cfg);
    buildGauges();
    buildEvents();
    connect();
    setInterval(watchdog, 250);
    setInterval(drawPlot, 100);
    window.addEventListener("resize", drawPlot);
    render();
  }

  // ---------------------------------------------------------------------- event stream
  const handlers = {
    snapshot(d) {
      ui.status = d.status;
      ui.io = new Map((d.io || []).map((p) => [p.name, p]));
      ui.diag = d.diag;
      ui.calibration = d.calibration || null;
      ui.link = d.link;
      ui.history = d.history || [];
      ui.sample = d.sample;
      clock(d.now);
      // Notices that came while this page was away (cut off for falling behind): a command
      // still waiting for its own ends now.
      for (const n of d.done || []) finished(n);
      if (ui.server.dropped) {
        // The server may have restarted with other options (e.g. --monitor): re-read them.
        ui.server.dropped = false;
        fetchConfig().then((cfg) => {
          if (cfg) {
            applyConfig(cfg);
            render();
          }
        });
      }
      setServer(true, "");
    },
    status(d) { ui.status = d; },
    io(points) { for (const p of points) ui.io.set(p.name, p); },
    diag(d) { ui.diag = d; },
    link(d) { ui.link = d; },
    sample(d) {
      const last = ui.history[ui.history.length - 1];
      if (!last || d.t > last.t) ui.history.push(d);
      const keep = d.t - (ui.cfg ? ui.cfg.history_s : 60);
      while (ui.history.length && ui.history[0].t < keep) ui.history.shift();
      ui.sample = d;
      clock(d.t);
    },
    tick(d) { clock(d.now); },
    done(d) { finished(d); },
    calibration(d) { ui.calibration = d; },
  };

  function connect() {
    if (ui.es) ui.es.close();
    const es = new EventSource("/api/events");
    ui.es = es;
    ui.server.lastMsg = performance.now();
    for (const [name, fn] of Object.entries(handlers)) {
      es.addEventListener(name, (e) => {
        if (ui.es !== es) return;
        ui.server.lastMsg = performance.now();
        let data;
        try {
          data = JSON.parse(e.data);
        } catch (err) {
          return;
        }
        fn(data);
        render();
      });
    }
    es.onerror = () => {
      if (ui.es !== es) return;
      drop("lost the connection to the UI server; reconnecting…");
    };
  }

  function drop(reason) {
    if (ui.es) ui.es.close();
    ui.es = null;
    ui.server.dropped = true;
    setServer(false, reason);
    if (!ui.retry) {
      ui.retry = setTimeout(() => {
        ui.retry = null;
        connect();
      }, 1000);
    }
  }

  function watchdog() {
    if (ui.es && performance.now() - ui.server.lastMsg > lostAfterMs()) {
      const secs = (lostAfterMs() / 1000).toFixed(1);
      drop(`no data from the UI server for over ${secs} s; reconnecting…`);
    }
  }

  function setServer(up, reason) {
    const changed = ui.server.up !== up || ui.server.reason !== reason;
    ui.server.up = up;
    ui.server.reason = reason;
    if (changed) render();
  }

  function clock(serverTime) {
    ui.server.time = serverTime;
    ui.server.at = performance.now();
  }

  const serverNow = () => ui.server.time + (performance.now() - ui.server.at) / 1000;

  // --------------------------------------------------------------------------- render
  function render() {
    renderLinks();
    renderState();
    renderBanners();
    renderSession();
    renderGauges();
    renderIo();
    renderDiag();
    renderButtons();
  }

  function renderLinks() {
    $("link-server").dataset.up = String(ui.server.up);
    $("link-machine").dataset.up = String(ui.server.up && ui.link.up);
    const id = ui.link.machine || (ui.status && ui.status.machine_id);
    $("machine-id").textContent = id || "…";
    $("main").dataset.stale = String(!live());
    const st = ui.status;
    $("uptime").textContent = st && live() ? `up ${duration(st.uptime_s)}` : "";
  }

  // Calibration values (machine/<id>/calibration): shown as the "calibrated" flags' tooltip.
  function calibrationText(c) {
    if (!c) return "";
    const how = (v) => ` (${v.source || "measured"}${v.at ? `, ${stamp(v.at)}` : ""})`;
    const t = c.tilt
      ? `tilt: offset ${c.tilt.offset_counts.toFixed(1)} counts, gain ${c.tilt.gain_counts_per_deg.toFixed(3)} counts/°${how(c.tilt)}${c.tilt.verified === false ? " NOT VERIFIED: the next Home verifies it" : ""}`
      : "tilt: not calibrated";
    const r = c.rotate
      ? `rotate: revolution ${c.rotate.revolution_s.toFixed(3)} s, home arc ${c.rotate.home_arc_deg.toFixed(1)}°${how(c.rotate)}`
      : "rotate: not calibrated";
    return `${t}\n${r}`;
  }

  function renderState() {
    const st = ui.status;
    const card = $("state-card");
    const label = card.querySelector(".card-label");
    if (!live()) {
      card.dataset.tone = "unknown";
      $("state").textContent = ui.server.up && !st ? "CONNECTING" : "NO CONNECTION";
      $("state").dataset.state = "";
      label.textContent = st ? `Machine state · last known ${words(st.state)}` : "Machine state";
    } else {
      card.dataset.tone = ui.cfg.tones[st.state] || "unknown";
      $("state").textContent = words(st.state);
      $("state").dataset.state = st.state;
      label.textContent = "Machine state";
    }
    $("prev-state").textContent = st && st.previous_state ? words(st.previous_state) : "—";
    $("calibrated").textContent = st ? flags(st.calibrated) : "—";
    $("calibrated").title = calibrationText(ui.calibration);
    $("homed").textContent = st ? flags(st.homed) : "—";
  }

  function renderBanners() {
    const lost = !live();
    show("banner-lost", lost);
    $("lost-reason").textContent = !ui.server.up ? ui.server.reason : ui.link.reason;
    const st = ui.status;
    let fault = null;
    if (!lost && st) {
      if (st.estop.active) {
        fault = ["E-STOP PRESSED", ui.cfg.estop_pressed];
      } else if (st.state === "FAULT_ESTOP" || st.estop.latched) {
        fault = ["E-STOP LATCHED", ui.cfg.hints.FAULT_ESTOP];
      } else if (st.fault) {
        const axis = st.fault.axis ? ` (${st.fault.axis} axis)` : "";
        fault = [`FAULT ${st.fault.code}`, `${st.fault.message}${axis}`];
      } else if (st.state === "FAULT_HW") {
        fault = ["FAULT", ui.cfg.hints.FAULT_HW];
      }
    }
    show("banner-fault", fault !== null);
    if (fault) {
      $("fault-title").textContent = fault[0];
      $("fault-reason").textContent = fault[1];
    }
    const warns = [];
    if (!lost && st) {
      if (st.state !== "FAULT_HW" && st.state !== "FAULT_ESTOP" && ui.cfg.hints[st.state]) {
        warns.push(ui.cfg.hints[st.state]);
      }
      warns.push(...st.warnings);
    }
    show("banner-warn", warns.length > 0);
    $("warn-reason").textContent = warns.join(" · ");
  }

  function renderSession() {
    const s = ui.status && ui.status.session;
    $("session-name").textContent = s ? s.name : "no session";
    $("step").textContent = s ? `${Math.min(s.step_index + 1, s.step_count)} / ${s.step_count}` +
      (s.step_kind ? ` ${s.step_kind}` : "") : "–";
    $("revs").textContent = s ? `${s.revolutions_done} / ${s.revolutions_total}` : "– / –";
    const pct = s && s.revolutions_total ? (100 * s.revolutions_done) / s.revolutions_total : 0;
    $("rev-bar").style.width = `${pct}%`;
    $("tilt-target").textContent = s && s.tilt_target_deg != null ? `${s.tilt_target_deg}°` : "—";
  }

  function renderIo() {
    const groups = { di: [], ai: [], ro: [] };
    for (const p of [...ui.io.values()].sort((a, b) => a.name.localeCompare(b.name))) {
      if (groups[p.kind]) groups[p.kind].push(p);
    }
    for (const kind of ["di", "ro"]) {
      const box = $(`io-${kind}`);
      sync(box, groups[kind], (p) => {
        const el = document.createElement("div");
        el.className = `lamp ${kind}`;
        el.innerHTML = "<i></i><span></span>";
        return el;
      }, (el, p) => {
        el.dataset.on = String(Boolean(p.value));
        el.id = `io-${p.name}`;
        el.title = `${p.name} (${p.channel}) = ${p.value ? 1 : 0}`;
        el.querySelector("span").innerHTML = "";
        el.querySelector("span").append(p.name, " ", small(p.channel));
      });
    }
    sync($("io-ai"), groups.ai, () => {
      const el = document.createElement("div");
      el.className = "analog";
      el.innerHTML = "<span></span><b></b>";
      return el;
    }, (el, p) => {
      el.id = `io-${p.name}`;
      el.querySelector("span").innerHTML = "";
      el.querySelector("span").append(p.name, " ", small(p.channel));
      el.querySelector("b").textContent = String(p.value);
    });
  }

  function renderDiag() {
    const d = ui.diag;
    const ms = (s) => (d ? `${(s * 1000).toFixed(2)} ms` : "—");
    $("d-period").textContent = d ? `${(d.period_s * 1000).toFixed(1)} ms` : "—";
    $("d-exec").textContent = ms(d && d.execution.p99);
    $("d-jitter").textContent = ms(d && d.jitter.p99);
    $("d-overruns").textContent = d ? String(d.overruns) : "—";
    $("d-overruns").dataset.bad = String(Boolean(d && d.overruns > 0));
    $("d-missed").textContent = d ? String(d.missed_cycles) : "—";
    $("d-missed").dataset.bad = String(Boolean(d && d.missed_cycles > 0));
    $("d-cycles").textContent = d ? d.cycles.toLocaleString("en") : "—";
  }

  // ------------------------------------------------------------------------- commands
  function buildCommands() {
    const monitor = ui.cfg.monitor;
    document.body.dataset.monitor = String(monitor);
    show("mode-badge", monitor);
    show("monitor-note", monitor);
    show("commands", !monitor);
    const box = $("buttons");
    box.innerHTML = "";
    // A button the machine would refuse now stays focusable (aria-disabled, its press refused
    // with the reason): one under the keyboard's focus keeps it when the machine moves on, and
    // Tab and a screen reader reach the visible line that says why (aria-describedby).
    for (const c of ui.cfg.commands) {
      const cell = document.createElement("div");
      cell.className = "cmd";
      const b = document.createElement("button");
      b.type = "button";
      b.id = `cmd-${c.key.replace("/", "-")}`;
      b.textContent = c.label;
      b.setAttribute("aria-disabled", "true");
      if (c.name === "Start") b.className = "go";
      if (c.name === "Pause") b.className = "hold";
      if (c.name === "Stop") b.className = "halt";
      b.addEventListener("click", () => press(c));
      const reason = document.createElement("span");
      reason.id = `why-${b.id}`;
      reason.className = "why";
      reason.hidden = true;
      cell.append(b, reason);
      box.append(cell);
    }
  }

  function buildSessions() {
    const sel = $("session-select");
    const keep = sel.value;
    sel.innerHTML = "";
    for (const s of [...ui.cfg.sessions, ...ui.uploaded]) {
      const o = document.createElement("option");
      o.value = s.id;
      o.textContent = s.label;
      sel.append(o);
    }
    if ([...sel.options].some((o) => o.value === keep)) sel.value = keep;
    $("session-file").onchange = upload;
  }

  async function upload(ev) {
    const file = ev.target.files[0];
    ev.target.value = "";
    if (!file) return;
    let session;
    try {
      const raw = JSON.parse(await file.text());
      session = raw && raw.session ? raw.session : raw;
    } catch (err) {
      result(false, `${file.name}: not valid JSON (${err.message})`);
      return;
    }
    const r = await post("/api/session", { session });
    if (!r.body.ok) {
      result(false, `${file.name}: ${r.body.error.message}`);
      return;
    }
    const id = `upload-${ui.uploaded.length + 1}`;
    ui.uploaded.push({ id, label: `Uploaded: ${r.body.session.name} (${file.name})`, session });
    buildSessions();
    $("session-select").value = id;
    result(true, `${file.name}: session “${r.body.session.name}” ready for Start`);
  }

  function chosenSession() {
    const id = $("session-select").value;
    return [...ui.cfg.sessions, ...ui.uploaded].find((s) => s.id === id) || ui.cfg.sessions[0];
  }

  const ESTOP_ACTIVE = "E-stop active";

  // Why no command can be sent now (the checks excepted, with the E-stop in): said once.
  function sharedReason() {
    if (ui.cfg.monitor) return "read-only monitor";
    if (!live()) return "not connected to the machine";
    if (ui.status.estop.active) return ESTOP_ACTIVE;
    return "";
  }

  function why(c) {
    const shared = sharedReason();
    if (shared && !(shared === ESTOP_ACTIVE && c.with_estop)) return shared;
    if (ui.busy.has(c.name)) return "sent, waiting for the reply";
    if (c.with_estop) return "";
    const st = ui.status;
    if (!c.states.includes(st.state)) return `accepted in ${c.states.map(words).join(", ")}`;
    return "";
  }

  // Each unavailable button is described by the visible line that says why: its own under it,
  // or the one above them all when the reason is the page's (no link, the E-stop).
  function renderButtons() {
    if (!ui.cfg) return;
    const shared = sharedReason();
    const common = $("commands-why");
    setText(common, shared ? `Unavailable now: ${shared}` : "");
    common.hidden = !shared;
    for (const c of ui.cfg.commands) {
      const b = $(`cmd-${c.key.replace("/", "-")}`);
      const reason = why(c);
      const line = $(`why-${b.id}`);
      const own = reason === shared ? "" : reason;
      b.setAttribute("aria-disabled", String(reason !== ""));
      setText(line, own);
      line.hidden = own === "";
      if (reason) b.setAttribute("aria-describedby", own ? line.id : common.id);
      else b.removeAttribute("aria-describedby");
      b.classList.toggle("busy", ui.busy.has(c.name));
    }
  }

  function setText(node, text) {
    if (node.textContent !== text) node.textContent = text;
  }

  async function press(c) {
    const now = why(c);
    if (now) {
      result(false, `${c.label} not sent: ${now}`);
      return;
    }
    let body = {};
    let question = c.confirm;
    if (c.name === "Start") {
      const s = chosenSession();
      body = { session: s.session };
      question = `${c.confirm}\n\nSession: ${s.label}`;
    }
    if (question && !(await confirmDialog(question))) return;
    const changed = why(c);
    if (changed) {
      // The machine moved on while the dialog was open: do not send a stale decision.
      result(false, `${c.label} not sent: ${changed}`);
      return;
    }
    await send(c.key, body);
  }

  function confirmDialog(question) {
    const dlg = $("confirm");
    $("confirm-text").textContent = question;
    return new Promise((resolve) => {
      dlg.addEventListener("close", () => resolve(dlg.returnValue === "ok"), { once: true });
      dlg.returnValue = "cancel";
      dlg.showModal();
      $("confirm-no").focus();
    });
  }

  async function send(key, body = {}) {
    const c = ui.cfg.commands.find((x) => x.key === key);
    const label = c ? c.label : key;
    if (c) ui.busy.add(c.name);
    renderButtons();
    try {
      const r = await post(`/api/cmd/${key}`, body);
      const d = r.body;
      if (d.ok) {
        let text = `${label}: ${humanCode(d.code)}`;
        if (d.result) {
          text = `${label}: tilt ${d.result.tilt ? "✔" : "✘"} · rotate ${d.result.rotate ? "✔" : "✘"}`;
        }
        result(true, text);
        // A motion ends with the completion notice of its own transaction (Resume continues
        // the motion in progress), never with a guess from the state.
        const motion = c && c.name === "Resume" && ui.status ? ui.status.motion : null;
        const tid = c && MOTIONS.has(c.name) ? d.transaction_id : motion && motion.transaction_id;
        if (tid) {
          ui.awaiting.set(tid, label);
          if (ui.notices.has(tid)) finished(ui.notices.get(tid));
        }
      } else {
        const e = d.error || { code: "ERROR", message: "refused" };
        result(false, `${label} refused — ${e.code}: ${e.message}`);
      }
      return d;
    } finally {
      if (c) ui.busy.delete(c.name);
      renderButtons();
    }
  }

  async function post(url, body) {
    try {
      const r = await fetch(url, {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify(body),
      });
      let data;
      try {
        data = await r.json();
      } catch (err) {
        data = { ok: false, error: { code: `HTTP_${r.status}`, message: r.statusText } };
      }
      return { status: r.status, body: data };
    } catch (err) {
      const error = { code: "NO_SERVER", message: "the UI server did not answer" };
      return { status: 0, body: { ok: false, error } };
    }
  }

  const MOTIONS = new Set(["Home", "CalibrateTilt", "CalibrateRotate", "Start"]);

  function finished(n) {
    ui.notices.set(n.transaction_id, n);
    while (ui.notices.size > 50) ui.notices.delete(ui.notices.keys().next().value);
    const label = ui.awaiting.get(n.transaction_id);
    if (label === undefined) return;
    ui.awaiting.delete(n.transaction_id);
    const why = n.reason ? ` (${n.reason})` : "";
    result(n.outcome === "DONE", `${label} finished: ${n.outcome}${why}`);
  }

  function result(ok, text) {
    const el = $("cmd-result");
    el.dataset.ok = String(ok);
    el.textContent = text;
    const li = document.createElement("li");
    const when = document.createElement("time");
    // The server's clock, as the events beside it are stamped (the browser's may differ).
    when.textContent = stamp(ui.server.time ? serverNow() : Date.now() / 1000);
    li.append(when, ` ${text}`);
    $("cmd-log").prepend(li);
    while ($("cmd-log").children.length > 5) $("cmd-log").lastChild.remove();
  }

  // --------------------------------------------------------------------------- gauges
  const TILT = { cx: 34, cy: 146, r: 118, lo: -10, hi: 100 };
  const ROT = { cx: 110, cy: 110, r: 92 };

  function el(tag, attrs, parent) {
    const node = document.createElementNS(SVG, tag);
    for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
    if (parent) parent.append(node);
    return node;
  }

  function tiltXY(deg, r) {
    // The seat seen from the side: 0° level (pointing right), 90° upright.
    const a = (deg * Math.PI) / 180;
    return [TILT.cx + r * Math.cos(a), TILT.cy - r * Math.sin(a)];
  }

  function rotXY(deg, r) {
    const a = ((deg - 90) * Math.PI) / 180; // 0° at the top, clockwise
    return [ROT.cx + r * Math.cos(a), ROT.cy + r * Math.sin(a)];
  }

  // A gauge's scale: a tick every `step` degrees from 0 to `to`, from radius `inner` to `outer`
  // (placed by `xy`), and `label: [every, radius]`, a label every so many degrees at that radius.
  function scale(svg, xy, { to, step, inner, outer, label: [labelEvery, labelAt] }) {
    for (let d = 0; d <= to; d += step) {
      const [ax, ay] = xy(d, inner);
      const [bx, by] = xy(d, outer);
      el("line", { class: "tick", x1: ax, y1: ay, x2: bx, y2: by }, svg);
      if (d % labelEvery === 0) {
        const [lx, ly] = xy(d, labelAt);
        el("text", { class: "tick-label", x: lx, y: ly }, svg).textContent = `${d}°`;
      }
    }
  }

  function buildGauges() {
    const t = $("gauge-tilt");
    t.innerHTML = "";
    const [x0, y0] = tiltXY(TILT.lo, TILT.r);
    const [x1, y1] = tiltXY(TILT.hi, TILT.r);
    el("path", { class: "arc", d: `M${x0},${y0} A${TILT.r},${TILT.r} 0 0 0 ${x1},${y1}` }, t);
    scale(t, tiltXY, { to: 90, step: 15, inner: TILT.r - 8, outer: TILT.r + 6, label: [30, TILT.r - 22] });
    el("polygon", { id: "tilt-target-mark", class: "target", points: "0,0 12,-7 12,7" }, t);
    const g = el("g", { id: "tilt-needle" }, t);
    el("line", { class: "needle", x1: TILT.cx, y1: TILT.cy, x2: TILT.cx + TILT.r - 14, y2: TILT.cy }, g);
    el("circle", { class: "needle-hub", cx: TILT.cx, cy: TILT.cy, r: 7 }, t);

    const r = $("gauge-rotate");
    r.innerHTML = "";
    el("circle", { class: "face", cx: ROT.cx, cy: ROT.cy, r: ROT.r + 8 }, r);
    scale(r, rotXY, { to: 330, step: 30, inner: ROT.r - 6, outer: ROT.r + 4, label: [90, ROT.r - 26] });
    const [hx, hy] = rotXY(0, ROT.r + 1);
    el("circle", { class: "home", cx: hx, cy: hy, r: 5 }, r);
    const n = el("g", { id: "rotate-needle" }, r);
    el("line", { class: "needle", x1: ROT.cx, y1: ROT.cy, x2: ROT.cx, y2: ROT.cy - ROT.r + 16 }, n);
    el("circle", { class: "needle-hub", cx: ROT.cx, cy: ROT.cy, r: 8 }, r);
  }

  // pnStatus bits (docs/fastdata.md): 1 settled, 2 moving, 4 drive enabled, 8 drive fault,
  // 16 position unknown.
  function axisState(bits) {
    if (bits & 8) return ["fault", "fault"];
    if (bits & 2) return ["moving", "moving"];
    if (bits & 16) return ["off", "position unknown"];
    if (bits & 1) return ["settled", bits & 4 ? "settled" : "settled, drive off"];
    if (bits & 4) return ["off", "stopped short"];
    return ["off", "drive off"];
  }

  function renderGauges() {
    const s = live() ? ui.sample : null;
    const tilt = s ? s.tilt : null;
    const rot = s ? s.rotate : null;
    const tn = $("tilt-needle");
    tn.style.visibility = tilt == null ? "hidden" : "visible";
    if (tilt != null) {
      const clamped = Math.max(TILT.lo, Math.min(TILT.hi, tilt));
      tn.setAttribute("transform", `rotate(${-clamped} ${TILT.cx} ${TILT.cy})`);
    }
    $("tilt-value").textContent = tilt == null ? "—" : `${tilt.toFixed(1)}°`;
    const target = ui.status && ui.status.session ? ui.status.session.tilt_target_deg : null;
    const mark = $("tilt-target-mark");
    mark.style.visibility = target == null || !live() ? "hidden" : "visible";
    if (target != null) {
      const [x, y] = tiltXY(target, TILT.r + 8);
      mark.setAttribute("transform", `translate(${x} ${y}) rotate(${-target})`);
    }
    const rn = $("rotate-needle");
    rn.style.visibility = rot == null ? "hidden" : "visible";
    if (rot != null) rn.setAttribute("transform", `rotate(${rot} ${ROT.cx} ${ROT.cy})`);
    $("rotate-value").textContent = rot == null ? "—" : `${rot.toFixed(0)}°`;
    for (const [axis, bits] of [["tilt", s ? s.tilt_bits : 0], ["rotate", s ? s.rotate_bits : 0]]) {
      const [cls, text] = s ? axisState(bits) : ["off", "—"];
      const badge = $(`${axis}-axis`);
      badge.dataset.s = cls;
      badge.textContent = text;
    }
  }

  // ----------------------------------------------------------------------------- plot
  const PLOT_COLOURS = {
    tilt: "#3fa7f5",
    moving: "rgba(63, 167, 245, 0.75)",
    settled: "#2f6d4b",
    off: "#4b5560",
    fault: "#d7263d",
    ok: "#1e9e57",
    warn: "#f2a900",
    unknown: "#5c6773",
  };

  function drawPlot() {
    const canvas = $("plot");
    if (!canvas || !ui.cfg || document.hidden) return;
    const dpr = window.devicePixelRatio || 1;
    const w = canvas.clientWidth;
    const h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const left = 64;
    const right = 8;
    const top = 8;
    const strip = 16;
    const strips = [["state", null], ["tilt axis", "tilt_bits"], ["rotate axis", "rotate_bits"]];
    const axisH = 18;
    const plotH = h - top - axisH - strips.length * (strip + 4) - 6;
    const span = ui.cfg.history_s;
    const now = serverNow();
    const x = (t) => left + ((t - (now - span)) / span) * (w - left - right);
    const lo = -10;
    const hi = 100;
    const y = (v) => top + plotH - ((v - lo) / (hi - lo)) * plotH;

    ctx.font = "11px system-ui, sans-serif";
    ctx.textBaseline = "middle";
    ctx.strokeStyle = "#2b3541";
    ctx.fillStyle = "#93a1b1";
    ctx.lineWidth = 1;
    for (const v of [0, 30, 60, 90]) {
      ctx.beginPath();
      ctx.moveTo(left, y(v));
      ctx.lineTo(w - right, y(v));
      ctx.stroke();
      ctx.textAlign = "right";
      ctx.fillText(`${v}°`, left - 6, y(v));
    }
    ctx.save();
    ctx.translate(12, top + plotH / 2);
    ctx.rotate(-Math.PI / 2);
    ctx.textAlign = "center";
    ctx.fillText("tilt", 0, 0);
    ctx.restore();

    const pts = ui.history.filter((p) => p.t >= now - span - 1);
    ctx.strokeStyle = PLOT_COLOURS.tilt;
    ctx.lineWidth = 2.5;
    ctx.beginPath();
    let pen = false;
    let prevT = null;
    for (const p of pts) {
      if (p.tilt == null || (prevT !== null && p.t - prevT > 0.6)) pen = false;
      prevT = p.t;
      if (p.tilt == null) continue;
      const px = x(p.t);
      const py = y(Math.max(lo, Math.min(hi, p.tilt)));
      if (pen) ctx.lineTo(px, py);
      else ctx.moveTo(px, py);
      pen = true;
    }
    ctx.stroke();

    let sy = top + plotH + 8;
    for (const [name, field] of strips) {
      ctx.fillStyle = "#121820";
      ctx.fillRect(left, sy, w - left - right, strip);
      ctx.fillStyle = "#93a1b1";
      ctx.textAlign = "right";
      ctx.fillText(name, left - 6, sy + strip / 2);
      for (let i = 0; i < pts.length; i += 1) {
        const p = pts[i];
        const next = pts[i + 1];
        const end = next && next.t - p.t <= 0.6 ? next.t : p.t + 0.1;
        const colour = field
          ? PLOT_COLOURS[axisState(p[field])[0]]
          : PLOT_COLOURS[ui.cfg.tones[p.state] === "moving" ? "ok" : ui.cfg.tones[p.state] || "unknown"];
        ctx.fillStyle = colour;
        const x0 = Math.max(left, x(p.t));
        ctx.fillRect(x0, sy, Math.max(1, x(end) - x0), strip);
      }
      sy += strip + 4;
    }

    ctx.fillStyle = "#93a1b1";
    ctx.textAlign = "center";
    for (let s = 0; s <= span; s += 15) {
      const label = s === 0 ? "now" : `−${s} s`;
      ctx.fillText(label, Math.min(w - right - 12, Math.max(left + 14, x(now - s))), h - axisH / 2);
    }
  }

  // --------------------------------------------------------------------------- events
  // The machine's event history (docs/events.md): the newest first, re-read every 2 s and at
  // once when the filter changes. The server says which ones are incidents (`tone`).

  function buildEvents() {
    const select = $("events-kind");
    for (const kind of (ui.cfg && ui.cfg.event_kinds) || []) {
      const o = document.createElement("option");
      o.value = kind;
      o.textContent = kind.replace(/_/g, " ");
      select.append(o);
    }
    select.addEventListener("change", loadEvents);
    loadEvents();
    setInterval(loadEvents, 2000);
  }

  async function loadEvents() {
    const kind = $("events-kind").value;
    const url = `/api/history?last=${(ui.cfg && ui.cfg.events_shown) || 50}` +
      (kind ? `&kind=${encodeURIComponent(kind)}` : "");
    let body;
    try {
      const r = await fetch(url, { cache: "no-store" });
      body = await r.json();
    } catch (err) {
      $("events-note").textContent = "the UI server is not answering";
      return;
    }
    if (kind !== $("events-kind").value) return; // the filter changed meanwhile
    if (!body.ok) {
      $("events-note").textContent = body.error ? body.error.message : "no history";
      return;
    }
    const rows = body.events.slice().reverse();
    $("events-note").textContent = rows.length ? "" : "no events";
    sync($("events-rows"), rows, () => {
      const li = document.createElement("li");
      for (const [tag, cls] of [["time", "ev-time"], ["span", "ev-seq"], ["span", "ev-kind"],
        ["span", "ev-text"]]) {
        const part = document.createElement(tag);
        part.className = cls;
        li.append(part);
      }
      return li;
    }, (li, e) => {
      const parts = li.children;
      parts[0].textContent = stamp(e.time);
      parts[1].textContent = `#${e.seq}`;
      parts[2].textContent = e.kind;
      parts[3].textContent = e.text;
      li.dataset.kind = e.kind;
      li.dataset.tone = e.tone || "";
    });
  }

  // -------------------------------------------------------------------------- helpers
  function show(id, visible) {
    $(id).hidden = !visible;
  }

  function words(state) {
    return String(state).replace(/_/g, " ");
  }

  function flags(f) {
    const mark = (v) => (v ? "✔" : "✘");
    return `tilt ${mark(f.tilt)} rotate ${mark(f.rotate)}`;
  }

  function humanCode(code) {
    return String(code).replace(/^RESP_/, "").replace(/_/g, " ").toLowerCase();
  }

  // One time format on the page, the one `rider events` prints: local time with milliseconds,
  // 2026-12-01 22:18:17.042 (rounded to the microsecond first, as Python's datetime does).
  function stamp(seconds) {
    const d = new Date(Math.floor(Math.round(seconds * 1e6) / 1e3));
    const two = (n) => String(n).padStart(2, "0");
    return `${d.getFullYear()}-${two(d.getMonth() + 1)}-${two(d.getDate())} ` +
      `${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}.` +
      String(d.getMilliseconds()).padStart(3, "0");
  }

  function duration(s) {
    if (s < 120) return `${Math.floor(s)} s`;
    if (s < 7200) return `${Math.floor(s / 60)} min`;
    return `${(s / 3600).toFixed(1)} h`;
  }

  function small(text) {
    const n = document.createElement("small");
    n.textContent = text;
    return n;
  }

  // Keep one child per item, in order, creating only what is missing.
  function sync(box, items, make, update) {
    while (box.children.length > items.length) box.lastChild.remove();
    items.forEach((item, i) => {
      let node = box.children[i];
      if (!node) {
        node = make(item);
        box.append(node);
      }
      update(node, item);
    });
  }

  window.riderUI = { send, ui, render };
  boot();
})();
