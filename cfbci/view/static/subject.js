"use strict";
// The subject view: the grid and the agent only, full screen, for the stimulus screen.
// /subject?session=ID follows ID; without it, the newest running session.
(() => {
  const pinned = new URLSearchParams(location.search).get("session");
  const view = document.getElementById("view");
  const message = document.getElementById("message");
  const world = new cfbci.WorldView(document.getElementById("world"), false);
  let model = null;
  let frame = null;

  const render = () => {
    frame = null;
    world.draw(model);
    message.textContent = model.status === "ended" ? "session ended" : "";
    cfbci.expose(view, model);
  };
  const link = cfbci.connect({
    link(up) { if (!up) message.textContent = "connection lost, reconnecting…"; },
    sessions(list) { link.follow(cfbci.choose(list, pinned, link.following)); },
    session(m) { model = m; if (!frame) frame = requestAnimationFrame(render); },
  });
  link.follow(pinned);

  const fullscreen = () => {
    if (document.fullscreenElement) document.exitFullscreen();
    else document.documentElement.requestFullscreen();
  };
  document.getElementById("fullscreen").onclick = fullscreen;
  document.addEventListener("keydown", (event) => { if (event.key === "f") fullscreen(); });
})();
