"""The pipeline service: runs a session's learner on the epochs its source sends.

A package of small parts, one job each:

- `cfbci.service.loop`: `PipelineService` (intake, dispatch, housekeeping,
  rejections); `cfbci.service.events` its events; `cfbci.service.main`
  `serve`, the main function of ``cfbci serve``;
- `cfbci.service.admission`: the checks a config passes before anything is built
  (limits, learner settings, one memory estimate for every world) and the configs waiting
  for their source;
- `cfbci.service.running`: a running session and an epoch's path (the session's
  checks, the features, the step of its `session.core.Session`, the move, state
  and events published and recorded);
- `cfbci.service.recordings`: the recordings, and the only reader of ``truth``;
- `cfbci.service.resume`: sessions recorded but unfinished, re-run and continued
  after a restart;
- `cfbci.service.priors`: the prior store (users' earlier recordings by SHA-256, their
  uploads, the checks of a config's prior).

The session's world, learner and random streams are its config's
(`session.sessions.open_session`): the agent's start state is the world's on the
session's user stream, the learner's stream is ``session_streams(seed)[2]``, and a
stochastic move takes the number of its step from the world stream, as ``cfbci simulate``
takes them, so that a live session replays a simulated one exactly.
"""

from cfbci.service.loop import PipelineService
from cfbci.service.main import serve
from cfbci.service.resume import unfinished

__all__ = ["PipelineService", "serve", "unfinished"]
