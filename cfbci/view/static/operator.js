"use strict";
// The operator view: the world with the belief heat map, the ranked hypotheses, the best
// task's confidence against the threshold, targets reached, the decoder's balanced accuracy,
// the update latency and the session's events. /?session=ID follows ID; without it, the
// newest running session (until one is picked; once none runs, the one shown stays).
// The session controls post the operator's commands (pause, resume, end, the target the
// subject chose) to the view's /control, which publishes them to the service; the
// service's answer comes back as the session's events (its status, or an error shown
// beside the buttons). Clicking a cell of the grid fills in the target.
(() => {
  const $ = (id) => document.getElementById(id);
  const view = $("view");
  const picker = $("picker");
  const world = new cfbci.WorldView($("world"), true);
  const COLOURS = {best: "#1f5fbf", threshold: "#c2410c", accuracy: "#0f766e", chance: "#6b7280",
                   latency: "#7c3aed", correct: "#15803d", wrong: "#b91c1c", pending: "#9ca3af"};
  let pinned = new URLSearchParams(location.search).get("session");
  let model = null;
  let frame = null;
  cfbci.colourBar($("colorbar-canvas"));
  $("subject-link").href = cfbci.link("/subject");

  const link = cfbci.connect({
    link(up) {
      $("link").textContent = up ? "live" : "disconnected";
      $("link").className = up ? "badge on" : "badge off";
    },
    sessions(list) {
      // Options are updated in place, so that an open drop-down stays open.
      const chosen = cfbci.choose(list, pinned, link.following);
      const wanted = list.map((s) => [s.session, `${s.session} (${s.status})`]);
      if (chosen && !list.some((s) => s.session === chosen)) wanted.push([chosen, chosen]);
      wanted.forEach(([value, text], i) => {
        const option = picker.options[i] || picker.appendChild(new Option());
        if (option.value !== value) option.value = value;
        if (option.text !== text) option.text = text;
      });
      while (picker.options.length > wanted.length) picker.remove(wanted.length);
      picker.value = chosen || "";
      link.follow(chosen);
    },
    session(m) { model = m; if (!frame) frame = requestAnimationFrame(render); },
  });
  link.follow(pinned);
  picker.onchange = () => {
    pinned = picker.value;
    history.replaceState(null, "", `?session=${encodeURIComponent(pinned)}`);
    link.follow(pinned);
  };
  const result = (text, refused) => {
    $("c-result").textContent = text;
    $("c-result").className = refused ? "muted refused" : "muted";
  };
  const command = async (name, extra = {}) => {
    if (!model) { result("no session followed", true); return; }
    // Noted before posting: the service may answer before the post returns.
    sent = {name, after: eventKey(model.events[model.events.length - 1])};
    try {
      const response = await fetch(cfbci.link("/control"), {
        method: "POST", headers: {"Content-Type": "application/json"},
        body: JSON.stringify({session: model.session, command: name, ...extra}),
      });
      const answer = await response.json();
      if (answer.error) { sent = null; result(`refused: ${answer.error}`, true); }
      else if (sent) result(`${name} sent, waiting for the service…`, false);
      if (sent && model) showAnswer(model);
    } catch (error) {
      sent = null;
      result(`not sent: ${error}`, true);
    }
  };
  let sent = null;  // the last command sent, and the newest event before it
  const eventKey = (e) => (e ? `${e.event}\n${e.message}` : "");
  $("c-pause").onclick = () => command("pause");
  $("c-resume").onclick = () => command("resume");
  $("c-end").onclick = () => {
    if (confirm(`End session ${model ? model.session : ""} now?`)) command("end");
  };
  $("c-mark").onclick = () => {
    const target = $("c-target").valueAsNumber;
    if (!Number.isInteger(target) || target < 0) { result("the target is a cell number", true); return; }
    command("target", {target});
  };
  $("world").addEventListener("click", (event) => {
    const cell = event.target.dataset && event.target.dataset.cell;
    if (cell !== undefined) $("c-target").value = cell;
  });
  const ANSWERS = {pause: "session_paused", resume: "session_resumed", end: "session_ended",
                   target: "target_marked"};
  const showAnswer = (m) => {
    // The service's answer to the last command: its event, or an error about a control.
    if (!sent) return;
    const start = sent.after ? m.events.map(eventKey).lastIndexOf(sent.after) + 1 : 0;
    const answer = m.events.slice(start).find((e) => e.event === ANSWERS[sent.name]
      || (e.event === "error" && e.message.includes("control")));
    if (answer) { result(answer.message, answer.event === "error"); sent = null; }
  };

  // Start a session: the settings posted to /start, checked by the view as the source
  // and the service would; a refusal is shown inline, a start followed at once. The source
  // is the simulated user or LSL streams (the view runs cfbci lsl-bridge, and shows that
  // command line). GET /start says whether the view may start sessions at all.
  const form = $("start-form");
  const NUMBERS = new Set(["grid", "steps", "seed", "accuracy", "interval", "tmin", "tmax",
                           "photodiode_threshold", "photodiode_window"]);
  const settingsOf = () => {
    const body = {learner: {}};
    for (const [name, value] of new FormData(form)) {  // a hidden source's are disabled
      if (name === "learner") {
        for (const pair of value.split(",").map((p) => p.trim()).filter((p) => p)) {
          const [key, ...rest] = pair.split("=");
          const text = rest.join("=").trim();
          try { body.learner[key.trim()] = JSON.parse(text); }
          catch { body.learner[key.trim()] = text; }
        }
      } else if (value !== "") {
        body[name] = NUMBERS.has(name) ? Number(value) : value;
      }
    }
    if (!body.photodiode) { delete body.photodiode_threshold; delete body.photodiode_window; }
    return body;
  };
  const shown = (id, text, refused) => {
    $(id).textContent = text;
    $(id).className = refused ? "muted refused" : "muted";
  };
  const getJSON = async (path) => (await fetch(cfbci.link(path))).json();
  const showStarted = async () => {
    const answer = await getJSON("/start");
    $("s-disabled").hidden = !answer.disabled;
    $("s-disabled").textContent = answer.disabled || "";
    $("s-fields").disabled = Boolean(answer.disabled);
    $("s-started").replaceChildren(...answer.started.map((s) => {
      const item = document.createElement("li");
      const state = s.exit === null ? "running" : `ended, exit status ${s.exit}`;
      item.textContent = `${s.session}: ${s.command ? "cfbci lsl-bridge" : "simulated user"}, ${state}`;
      if (s.command) item.title = s.command;
      return item;
    }));
  };
  const lookForStreams = async () => {
    shown("s-streams-result", "looking…", false);
    const answer = await getJSON("/lsl-streams");
    if (answer.error) { shown("s-streams-result", answer.error, true); return; }
    shown("s-streams-result", `${answer.streams.length} found`, false);
    $("s-streams").tBodies[0].replaceChildren(...answer.streams.map((s) => {
      const row = document.createElement("tr");
      for (const text of [s.name, s.type, s.channels, s.rate || "irregular", s.host]) {
        row.insertCell().textContent = text;
      }
      row.className = s.role;
      row.title = {eeg: "click: the EEG stream", markers: "click: the onset-marker stream",
                   other: "neither EEG (a numeric stream with a rate) nor markers (strings)"}[s.role];
      row.onclick = () => {
        if (s.role !== "other") form.elements[s.role === "eeg" ? "eeg" : "markers"].value = s.name;
      };
      return row;
    }));
    for (const [list, role] of [["s-eeg-names", "eeg"], ["s-marker-names", "markers"]]) {
      $(list).replaceChildren(...answer.streams.filter((s) => s.role === role)
        .map((s) => new Option(`${s.type}, ${s.channels} ch, ${s.host}`, s.name)));
    }
  };
  form.elements.source.onchange = () => {
    const source = form.elements.source.value;
    for (const set of form.querySelectorAll("fieldset[data-source]")) {
      set.hidden = set.disabled = set.dataset.source !== source;
    }
    if (source === "lsl") lookForStreams();
  };
  $("s-look").onclick = lookForStreams;
  $("start").addEventListener("toggle", () => { if ($("start").open) showStarted(); });
  setInterval(() => { if ($("start").open) showStarted(); }, 3000);  // the sources' states
  form.onsubmit = async (event) => {
    event.preventDefault();
    shown("s-result", "checking…", false);
    $("s-command").textContent = "";
    try {
      const response = await fetch(cfbci.link("/start"), {
        method: "POST", headers: {"Content-Type": "application/json"},
        body: JSON.stringify(settingsOf()),
      });
      const answer = await response.json();
      if (answer.error) { shown("s-result", `refused: ${answer.error}`, true); return; }
      shown("s-result", `started ${answer.started}`, false);
      if (answer.command) $("s-command").textContent = `the same from a terminal: ${answer.command}`;
      pinned = answer.started;
      history.replaceState(null, "", `?session=${encodeURIComponent(pinned)}`);
      link.follow(pinned);
      showStarted();
    } catch (error) {
      shown("s-result", `not started: ${error}`, true);
    }
  };

  window.addEventListener("resize", () => { if (model && !frame) frame = requestAnimationFrame(render); });

  const cellName = (m, task) => {
    if (m.layout.kind !== "grid") return `hypothesis ${task}`;
    const side = m.layout.side;
    return `cell ${task} (row ${Math.floor(task / side)}, col ${task % side})`;
  };
  const percentile = (values, q) => {
    const sorted = [...values].sort((a, b) => a - b);
    return sorted[Math.min(sorted.length - 1, Math.floor(q * sorted.length))];
  };

  function render() {
    frame = null;
    const m = model;
    world.draw(m);
    $("world-title").textContent = m.layout.kind !== "grid"
      ? `Agent's state (${m.steps === null ? "config not seen" : "no grid in the config"})`
      : `Belief over targets (${m.layout.side} × ${m.layout.side} grid`
        + `${m.layout.inferred ? ", inferred: config not seen" : ""})`;
    $("colorbar").style.display = $("legend").style.display = m.layout.kind === "grid" ? "" : "none";
    $("status").textContent = m.status;
    $("status").className = `badge ${m.status}`;
    const live = m.status === "running" || m.status === "paused";
    $("c-pause").disabled = m.status !== "running";
    $("c-resume").disabled = m.status !== "paused";
    $("c-end").disabled = $("c-mark").disabled = !live;
    showAnswer(m);
    $("subject-link").href = cfbci.link("/subject", {session: m.session});
    $("truth-key").style.display = m.truth_hidden ? "none" : "";

    const {correct, wrong} = m;
    const pending = m.targets.filter((t) => t.status === "pending").length;
    $("t-step").textContent = `${m.step}${m.steps ? ` / ${m.steps}` : ""}`;
    $("t-targets").innerHTML = m.truth_hidden
      ? `${pending} <span class="muted">(truth hidden)</span>`
      : `<span class="ok">✓ ${correct}</span> <span class="bad">✗ ${wrong}</span>`
        + (pending ? ` <span class="muted">(${pending} awaiting truth)</span>` : "");
    $("t-best").textContent = m.best_task === null ? "–"
      : `${m.best_task} · ${m.confidence[m.best_task].toFixed(3)}${m.confident ? " ✔" : ""}`;
    $("t-bacc").textContent = m.balanced_accuracy === null ? "–" : m.balanced_accuracy.toFixed(3);
    const ms = m.latency.map((p) => p[1]);
    $("t-latency").textContent = ms.length
      ? `${percentile(ms, 0.5).toFixed(1)} · ${percentile(ms, 0.9).toFixed(1)} ms` : "–";

    const ranked = m.confidence.map((c, task) => [c, task]).sort((a, b) => b[0] - a[0])
      .slice(0, m.layout.kind === "grid" ? 5 : 10);
    $("ranking").replaceChildren(...ranked.map(([c, task]) => {
      const item = document.createElement("li");
      item.innerHTML = `<span class="name"></span><span class="bar"><i></i></span><span class="num"></span>`;
      item.querySelector(".name").textContent = cellName(m, task);
      item.querySelector(".bar i").style.width = `${(100 * c).toFixed(1)}%`;
      item.querySelector(".num").textContent = c.toFixed(3);
      item.dataset.task = task;
      return item;
    }));

    const lastStep = Math.max(m.steps || 0, m.step, 10);
    const marks = m.targets.map((t) => ({x: t.step, colour: COLOURS[t.status]}));
    charts.draw($("c-confidence"), {
      title: "Confidence of the best task", xLabel: "step (epochs observed)",
      yLabel: "confidence", x: [0, lastStep], y: [0, 1],
      lines: [{points: m.series.map((p) => [p[0], p[1]]), colour: COLOURS.best, label: "best task"}],
      refs: [{y: m.threshold, colour: COLOURS.threshold,
              label: `threshold β = ${m.threshold}${m.threshold_known ? "" : " (default)"}`}],
      marks,
      keys: m.truth_hidden ? [{colour: COLOURS.pending, label: "target (truth hidden)"}]
        : [{colour: COLOURS.correct, label: "correct target"},
           {colour: COLOURS.wrong, label: "wrong target"}],
      empty: "no beliefs yet",
    });
    const chance = m.n_classes ? 1 / m.n_classes : null;
    charts.draw($("c-accuracy"), {
      title: "Decoder balanced accuracy (best task, 10-fold, self-estimate)",
      xLabel: "step (epochs observed)", yLabel: "balanced accuracy", x: [0, lastStep], y: [0, 1],
      lines: [{points: m.series.filter((p) => p[2] !== null).map((p) => [p[0], p[2]]),
               colour: COLOURS.accuracy, label: "balanced accuracy"}],
      refs: chance === null ? [] : [{y: chance, colour: COLOURS.chance, label: `chance ${chance}`}],
      empty: "no decoder yet",
    });
    charts.draw($("c-latency"), {
      title: "Update latency: epoch k received → move k + 1 received (by this view)",
      xLabel: "step", yLabel: "latency (ms)", x: [0, lastStep],
      y: [0, Math.max(1, ...ms) * 1.1],
      lines: [{points: m.latency, colour: COLOURS.latency, label: "latency"}],
      empty: "no epochs received by the view",
    });

    $("events").replaceChildren(...[...m.events].reverse().map((e) => {
      const item = document.createElement("li");
      item.className = e.event;
      item.textContent = `${e.event}: ${e.message}`;
      return item;
    }));

    cfbci.expose(view, m);
    Object.assign(view.dataset, {correct, wrong, best: m.best_task === null ? "" : m.best_task});
  }
})();
