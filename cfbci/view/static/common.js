"use strict";
// Shared by the operator and subject pages: the access token, the WebSocket link to
// `cfbci view`, the session model that the server's snapshots and patches keep up to date,
// and the drawing of the world (a grid in SVG, or the agent's state for a world without a
// grid).

const cfbci = (() => {
  const SVG = "http://www.w3.org/2000/svg";

  // The access token, when the page's address carries it (?token=...): taken out of the
  // address bar (the cookie the server set keeps a reload working) and passed on to the
  // WebSocket and to the links this page makes.
  const address = new URL(location.href);
  const token = address.searchParams.get("token");
  if (token !== null) {
    address.searchParams.delete("token");
    history.replaceState(null, "", address.pathname + address.search + address.hash);
  }

  /** A path of the view with these query parameters, and the token when the page has it. */
  function link(path, params = {}) {
    const query = new URLSearchParams(params);
    if (token !== null) query.set("token", token);
    const text = query.toString();
    return text ? `${path}?${text}` : path;
  }

  /**
   * Apply a server patch ({set, append} or {reset}) to a session model, in place; a series
   * keeps its newest model.series_length points, as the server does.
   */
  function apply(model, patch) {
    if (patch.reset) {
      for (const key of Object.keys(model)) delete model[key];
      Object.assign(model, patch.reset);
      return;
    }
    Object.assign(model, patch.set || {});
    for (const [key, items] of Object.entries(patch.append || {})) {
      model[key].push(...items);
      const excess = model[key].length - model.series_length;
      if (excess > 0) model[key].splice(0, excess);
    }
  }

  /**
   * Open the WebSocket (reconnecting after a loss) and follow one session at a time.
   * handlers.link(up), handlers.sessions(list), handlers.session(model) are called as things
   * arrive. Returns {follow(id)}.
   */
  function connect(handlers) {
    let socket = null;
    let wanted = null;
    let model = null;
    const send = () => {
      if (wanted && socket && socket.readyState === WebSocket.OPEN) {
        socket.send(JSON.stringify({follow: wanted}));
      }
    };
    const receive = (message) => {
      if (message.type === "sessions") {
        handlers.sessions(message.sessions);
      } else if (message.type === "snapshot" && message.session === wanted) {
        model = message;
        handlers.session(model);
      } else if (message.type === "update" && model && message.session === model.session) {
        apply(model, message);
        handlers.session(model);
      } else if (message.type === "error") {
        console.warn(message.message);
      }
    };
    const open = () => {
      const scheme = location.protocol === "https:" ? "wss" : "ws";
      socket = new WebSocket(`${scheme}://${location.host}${link("/ws")}`);
      socket.onopen = () => { handlers.link(true); model = null; send(); };
      socket.onclose = () => { handlers.link(false); setTimeout(open, 1000); };
      socket.onmessage = (event) => receive(JSON.parse(event.data));
    };
    open();
    return {
      follow(id) {
        if (id && id !== wanted) { wanted = id; model = null; send(); }
      },
      /** The session followed now, or null. */
      get following() { return wanted; },
    };
  }

  /**
   * The session to show: the pinned one, else the newest running, else the one shown now
   * (a session that has just ended stays in view), else the newest.
   */
  function choose(sessions, pinned, shown) {
    if (pinned) return pinned;
    const running = sessions.filter((s) => s.status === "running");
    if (running.length) return running[running.length - 1].session;
    if (shown && sessions.some((s) => s.session === shown)) return shown;
    return sessions.length ? sessions[sessions.length - 1].session : null;
  }

  // Viridis (perceptually uniform, colour-blind safe), 9 control points.
  const VIRIDIS = [
    [68, 1, 84], [71, 44, 122], [59, 81, 139], [44, 113, 142], [33, 144, 141],
    [39, 173, 129], [92, 200, 99], [170, 220, 50], [253, 231, 37],
  ];
  function viridis(t) {
    const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
    const i = Math.min(Math.floor(x), VIRIDIS.length - 2);
    const f = x - i;
    const c = VIRIDIS[i].map((v, k) => Math.round(v + f * (VIRIDIS[i + 1][k] - v)));
    return `rgb(${c[0]},${c[1]},${c[2]})`;
  }

  function svg(name, attributes = {}) {
    const element = document.createElementNS(SVG, name);
    for (const [key, value] of Object.entries(attributes)) element.setAttribute(key, value);
    return element;
  }

  /**
   * The world in a container: a grid of cells (row * side + col, row 0 at the top) with the
   * agent, or, for a world without a grid, the agent's state as text. With `heat`, cells are
   * coloured by the confidence of each target and the path, the best task and the user's
   * target are marked (operator); without, only the grid and the agent (subject).
   */
  class WorldView {
    constructor(container, heat) {
      this.container = container;
      this.heat = heat;
      this.side = null;
    }

    build(side) {
      this.side = side;
      this.container.replaceChildren();
      const root = svg("svg", {viewBox: `-0.05 -0.05 ${side + 0.1} ${side + 0.1}`,
                               class: "grid", preserveAspectRatio: "xMidYMid meet"});
      this.cells = [];
      for (let cell = 0; cell < side * side; cell++) {
        const rect = svg("rect", {x: (cell % side) + 0.03, y: Math.floor(cell / side) + 0.03,
                                  width: 0.94, height: 0.94, rx: 0.06, class: "cell",
                                  "data-cell": cell});
        root.append(rect);
        this.cells.push(rect);
      }
      this.path = svg("polyline", {class: "path"});
      this.best = svg("rect", {width: 0.94, height: 0.94, rx: 0.06, class: "best"});
      this.truth = svg("rect", {width: 0.8, height: 0.8, rx: 0.12, class: "truth"});
      this.agent = svg("circle", {r: 0.3, cx: 0, cy: 0, class: "agent"});
      if (this.heat) root.append(this.path, this.best, this.truth);
      root.append(this.agent);
      this.container.append(root);
    }

    centre(cell) {
      return [(cell % this.side) + 0.5, Math.floor(cell / this.side) + 0.5];
    }

    place(element, cell, size) {
      if (cell === null || cell === undefined) { element.style.display = "none"; return; }
      const [x, y] = this.centre(cell);
      element.style.display = "";
      element.setAttribute("x", x - size / 2);
      element.setAttribute("y", y - size / 2);
    }

    draw(model) {
      if (model.layout.kind !== "grid") { this.drawState(model); return; }
      if (this.side !== model.layout.side) this.build(model.layout.side);
      const confidence = model.confidence;
      this.cells.forEach((rect, cell) => {
        const known = this.heat && confidence.length === this.cells.length;
        rect.style.fill = known ? viridis(confidence[cell]) : "";
      });
      if (model.agent === null) {
        this.agent.style.display = "none";
      } else {
        const [x, y] = this.centre(model.agent);
        this.agent.style.display = "";
        this.agent.style.transform = `translate(${x}px, ${y}px)`;
      }
      if (!this.heat) return;
      this.path.setAttribute("points",
                             model.path.map((cell) => this.centre(cell).join(",")).join(" "));
      this.place(this.best, model.best_task, 0.94);
      this.place(this.truth, model.user_target, 0.8);
    }

    drawState(model) {
      this.side = null;
      let text = this.container.querySelector(".state");
      if (!text) {
        this.container.replaceChildren();
        text = document.createElement("div");
        text.className = "state";
        this.container.append(text);
      }
      text.textContent = model.agent === null ? "–" : `state ${model.agent}`;
    }
  }

  /** Draw the viridis colour bar into a canvas. */
  function colourBar(canvas) {
    const context = canvas.getContext("2d");
    for (let x = 0; x < canvas.width; x++) {
      context.fillStyle = viridis(x / (canvas.width - 1));
      context.fillRect(x, 0, 1, canvas.height);
    }
  }

  /** Set the data-* attributes that tell what the page shows (read by tests, too). */
  function expose(element, model) {
    const data = element.dataset;
    data.session = model.session;
    data.status = model.status;
    data.step = model.step;
    data.agent = model.agent === null ? "" : model.agent;
    data.layout = model.layout.kind;
  }

  return {apply, connect, choose, link, viridis, colourBar, expose, WorldView};
})();
