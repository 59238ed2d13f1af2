"use strict";
// The subject page as the stimulus program (`cfbci view --stimulus`, see
// cfbci/view/stimulus.py): the moves of cfbci lsl-bridge shown full screen, each in one
// frame whose start (the requestAnimationFrame timestamp) is reported to the server, which
// sends the onset marker on LSL at that time mapped to the LSL clock.
//
// The page measures its refresh period (the median interval between animation frames) and
// checks the frame that shows a move: the page must be visible, and neither the interval
// before that frame nor the one after it may exceed `frame_tolerance` periods (a dropped
// frame); otherwise the onset is reported invalid and the server sends the move again.
// Each show is marked in the page's performance timeline: performance.mark("onset <step>")
// in the frame that shows it, at the frame's timestamp (its startTime), for a trace of
// Chromium's to be compared with the LSL markers (cfbci bench timing).

const cfbciStimulus = (() => {
  const SVG = "http://www.w3.org/2000/svg";
  const FRAMES_KEPT = 120;  // frame intervals the refresh period is the median of
  const FRAMES_NEEDED = 10;  // intervals measured before the first show

  function svg(name, attributes = {}) {
    const element = document.createElementNS(SVG, name);
    for (const [key, value] of Object.entries(attributes)) element.setAttribute(key, value);
    return element;
  }

  function median(values) {
    const sorted = [...values].sort((a, b) => a - b);
    const middle = sorted.length >> 1;
    return sorted.length % 2 ? sorted[middle] : (sorted[middle - 1] + sorted[middle]) / 2;
  }

  // Where the agent is drawn after a move: the new cell; a move into a wall is drawn as a
  // bump a quarter cell towards it, and the declaration ("goal") fills the cell.
  const BUMP = {up: [0, -0.25], down: [0, 0.25], left: [-0.25, 0], right: [0.25, 0]};

  /** The grid of the stimulus: cells, target, fixation cross and agent, in SVG. */
  class Scene {
    constructor(container, settings) {
      const side = settings.grid;
      this.side = side;
      const root = svg("svg", {viewBox: `-0.05 -0.05 ${side + 0.1} ${side + 0.1}`,
                               class: "grid stimulus", preserveAspectRatio: "xMidYMid meet"});
      for (let cell = 0; cell < side * side; cell++) {
        root.append(svg("rect", {x: (cell % side) + 0.03, y: Math.floor(cell / side) + 0.03,
                                 width: 0.94, height: 0.94, rx: 0.06, class: "cell"}));
      }
      if (settings.target !== null) {
        const [x, y] = this.centre(settings.target);
        root.append(svg("rect", {x: x - 0.42, y: y - 0.42, width: 0.84, height: 0.84,
                                 rx: 0.1, class: "target"}));
      }
      this.declared = svg("rect", {width: 0.94, height: 0.94, rx: 0.06, class: "declared"});
      this.declared.style.display = "none";
      root.append(this.declared);
      if (settings.fixation) {
        const c = side / 2;
        root.append(svg("path", {d: `M${c - 0.12} ${c}H${c + 0.12}M${c} ${c - 0.12}V${c + 0.12}`,
                                 class: "fixation"}));
      }
      // The photodiode patch: a square in the bottom-left corner, black but white for
      // `patch_frames` frames from each onset's frame (none without it).
      this.patch = null;
      if (settings.patch_frames) {
        this.patch = document.createElement("div");
        this.patch.id = "photodiode-patch";
        Object.assign(this.patch.style, {position: "fixed", left: "0", bottom: "0",
                                         width: "2cm", height: "2cm", background: "black",
                                         zIndex: "10"});
        document.body.append(this.patch);
      }
      this.agent = svg("circle", {r: 0.3, cx: 0.5, cy: 0.5, class: "agent"});
      this.agent.style.display = "none";
      root.append(this.agent);
      container.replaceChildren(root);
      this.drawn = null;  // what is drawn: {cell, action, declared}
    }

    centre(cell) {
      return [(cell % this.side) + 0.5, Math.floor(cell / this.side) + 0.5];
    }

    /** Draw the agent in `cell`, bumped by `action` (or null) or declaring the cell. */
    draw(cell, action = null, declared = false) {
      const [x, y] = this.centre(cell);
      const [dx, dy] = (action && BUMP[action]) || [0, 0];
      this.agent.setAttribute("cx", x + dx);
      this.agent.setAttribute("cy", y + dy);
      this.agent.style.display = "";
      this.declared.style.display = declared ? "" : "none";
      this.declared.setAttribute("x", x - 0.47);
      this.declared.setAttribute("y", y - 0.47);
      this.drawn = {cell, action, declared};
    }

    /** Whether the agent is drawn plainly in `cell`. */
    plainlyAt(cell) {
      const drawn = this.drawn;
      return drawn !== null && drawn.cell === cell && drawn.action === null && !drawn.declared;
    }
  }

  /**
   * Run the stimulus in `container`, telling what it does in `view`'s data-* attributes
   * (stimulus: "waiting", "on" or "refused"; shows; step). Calls onActive() once the server
   * has made this page the stimulus.
   */
  function start(container, view, onActive) {
    let socket = null;
    let settings = null;
    let scene = null;
    const intervals = [];
    let last = null;  // the previous frame's timestamp, ms
    let pending = null;  // the show to make: {show, move, due}
    let checking = null;  // the show made in the last frame, its frame's interval unknown
    let hidden = false;  // the page was hidden since the last show
    let lastShow = -Infinity;  // page time of the last show's frame, ms
    let shows = 0;
    let lit = 0;  // frames the photodiode patch stays white
    view.dataset.stimulus = "waiting";

    const send = (message) => {
      if (socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
    };

    const schedule = (show, move) => {
      let since = lastShow;
      if (!scene.plainlyAt(move.from_state)) {  // a new start, or the move shown again
        scene.draw(move.from_state);
        since = Math.max(since, performance.now());
      }
      // Never in a frame that began before the move came: its timestamp (the onset)
      // would precede the move, which the bridge ignores as no onset of it.
      pending = {show, move, due: Math.max(since + settings.interval_ms, performance.now())};
    };

    const check = (made, after, period) => {
      const limit = settings.frame_tolerance * period;
      let reason = null;
      if (hidden || made.hidden || document.visibilityState !== "visible") reason = "hidden";
      else if (made.before > limit || after > limit) reason = "dropped frame";
      send({type: "onset", show: made.show, step: made.move.step, repeat: made.move.repeat,
            frame_ms: made.frame, valid: reason === null, reason, period_ms: period,
            before_ms: made.before, after_ms: after});
    };

    const frame = (t) => {
      const interval = last === null ? null : t - last;
      last = t;
      if (interval !== null) {
        intervals.push(interval);
        if (intervals.length > FRAMES_KEPT) intervals.shift();
      }
      const period = intervals.length ? median(intervals) : null;
      if (checking !== null) {
        check(checking, interval, period);
        checking = null;
      }
      if (lit > 0 && --lit === 0) scene.patch.style.background = "black";
      const steady = intervals.length >= FRAMES_NEEDED
        && interval <= settings.frame_tolerance * period
        && document.visibilityState === "visible";
      if (pending !== null && t >= pending.due && steady) {
        const move = pending.move;
        const declared = move.action === "goal";
        const bumped = !declared && move.to_state === move.from_state;
        scene.draw(move.to_state, bumped ? move.action : null, declared);
        if (scene.patch !== null) {
          scene.patch.style.background = "white";
          lit = settings.patch_frames;
        }
        performance.mark(`onset ${move.step}`, {startTime: t, detail: {repeat: move.repeat}});
        checking = {...pending, frame: t, before: interval,
                    hidden: document.visibilityState !== "visible"};
        hidden = false;
        lastShow = t;
        pending = null;
        shows += 1;
        view.dataset.shows = shows;
        view.dataset.step = move.step;
      }
      requestAnimationFrame(frame);
    };

    const receive = (message) => {
      if (message.type === "ping") {
        send({type: "pong", id: message.id, page_ms: performance.now()});
      } else if (message.type === "show" && scene !== null) {
        schedule(message.show, message.move);
      } else if (message.type === "stimulus" && message.settings) {
        if (settings === null) {
          settings = message.settings;
          scene = new Scene(container, settings);
          requestAnimationFrame(frame);
        }
        view.dataset.stimulus = "on";
        onActive();
      } else if (message.type === "stimulus") {
        view.dataset.stimulus = "refused";
        console.warn(`not the stimulus: ${message.refused}`);
      }
    };

    document.addEventListener("visibilitychange", () => {
      if (document.visibilityState !== "visible") hidden = true;
    });
    const open = () => {
      const scheme = location.protocol === "https:" ? "wss" : "ws";
      socket = new WebSocket(`${scheme}://${location.host}${cfbci.link("/stimulus")}`);
      let opened = false;
      socket.onopen = () => { opened = true; send({type: "stimulus"}); };
      socket.onmessage = (event) => receive(JSON.parse(event.data));
      // A view without --stimulus has no /stimulus: its socket never opens, and the page
      // stays the plain subject view. A lost stimulus socket is opened again.
      socket.onclose = () => {
        pending = null;
        checking = null;
        if (opened) setTimeout(open, 1000);
      };
    };
    open();
  }

  return {start};
})();
