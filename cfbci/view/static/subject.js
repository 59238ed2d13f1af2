"use strict";
// The subject view: the grid and the agent only, full screen, for the stimulus screen.
// /subject?session=ID follows ID; without it, the newest running session. When the view
// runs with --stimulus, the page is the stimulus program (stimulus.js): the grid shows the
// moves of cfbci lsl-bridge's move stream, each timed by the frame that shows it, and the
// session followed only gives the status line.
(() => {
  const pinned = new URLSearchParams(location.search).get("session");
  const view = document.getElementById("view");
  const message = document.getElementById("message");
  const container = document.getElementById("world");
  const world = new cfbci.WorldView(container, false);
  let model = null;
  let frame = null;
  let stimulus = false;

  const render = () => {
    frame = null;
    if (!stimulus) world.draw(model);
    message.textContent = {ended: "session ended", paused: "paused"}[model.status] || "";
    cfbci.expose(view, model);
  };
  const link = cfbci.connect({
    link(up) { if (!up) message.textContent = "connection lost, reconnecting…"; },
    sessions(list) { link.follow(cfbci.choose(list, pinned, link.following)); },
    session(m) { model = m; if (!frame) frame = requestAnimationFrame(render); },
  });
  link.follow(pinned);
  cfbciStimulus.start(container, view, () => {
    stimulus = true;
    document.body.classList.add("stimulus");
    if (model === null) message.textContent = "";
  });

  const fullscreen = () => {
    if (document.fullscreenElement) document.exitFullscreen();
    else document.documentElement.requestFullscreen();
  };
  document.getElementById("fullscreen").onclick = fullscreen;
  document.addEventListener("keydown", (event) => { if (event.key === "f") fullscreen(); });
})();
