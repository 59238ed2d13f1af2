"""An upper estimate of the memory one session's learner commits, term by term.

The service checks it against its ``max_session_mb`` limit (`cfbci.service.limits`). It
follows the learner's data structures (`calibration_free.task_decoders`,
`calibration_free.learner`, `calibration_free.frames`,
`calibration_free.planning`) as functions of the sizes of the world (T tasks, S
states, A actions), the frame (K classes; K' = K + 1 for guidance, whose labels leave some
signals unlabelled, a class of their own in the pooled fit), the learner settings (F folds,
J = F + 1 training sets: each fold's and the whole history's; m planning signals), the
steps n and the feature length d. Counts are of float64 numbers (8 bytes) unless said.

The world's tables are resident for the whole session. On top of them comes the larger of
two peaks that never overlap: **building** the tables (once, at the first epoch, before any
statistic exists) and a **step**: the history (resident from the first epoch on) plus the
largest of the step's phases, its fit, its cross-validation and its planning (one after
the other, each freeing its temporaries before the next). Each phase's term counts the
arrays alive at once at its peak, read from the code (the counts below); their element
counts are exact, so the arrays' sum bounds what the learner allocates (pages never
written, e.g. of ``np.zeros``, are not even resident). The allocator's slack
(`SLACK` of the arrays) and a constant `OVERHEAD_BYTES` are added. With
u = T K d, u' = T K' d, v = T K d² and w = T K n d:

* world tables: ``optimal`` T S A booleans (+ guidance's row table, T S bytes);
  building them: by value iteration (non-grid worlds) about 5 float arrays of the tasks
  solved at once (E = min(T, 2^22 / (S A)) S A elements) and more with several outcomes;
  the grid's closed form 4 S² integers and 5 E bytes;
* history: the signals and every task's label weights (capacity doubling from 64: 1.5
  capacities at the doubling), per fold and task the class counts and sums (J u), and for
  the per-class-scatter decoders (Student-t, Gaussian) and the Bhattacharyya likelihood the
  class scatter matrices (J v), each with one step's increment; guidance's label re-split:
  the frame's labels (T K per capacity), 4 T n K and the rebuilt F u (and F v);
* fit (per step): pooled LDA (and categorical) 3 J u + 4 J u' (the pooled statistics'
  sums, their projection, its scaled copy, the small solve's result, the coefficients
  twice) and 4 J T d (the shrunk eigenvalues per task, the unlabelled signals' sums);
  per-class decoders (1 + 6 F) v (the whole history's and the folds' training scatters,
  then per fold the covariances, shrunk scatters, scales, their Cholesky factors and
  inverses); the Bhattacharyya likelihood's overlaps 5 v (class statistics and moments of
  every task);
* cross-validation (per step, always: the service reports every step's cross-validated
  balanced accuracy): all J decoders, the out-of-fold scores (4 T n K; 2 for two-class
  LDA) and, for per-class decoders, 3 w (every signal centred on every class mean, times
  the precision);
* planning: the whole history's decoders and out-of-fold predictions, the uncertainty or
  signal planner's indicator chunk (T x min(S A or S, 2^22 / T) columns: 9 bytes each)
  and its value iteration. The uncertainty and information planners keep their row
  indicators from the first step on where they fit in
  `KEPT_INDICATOR_BYTES` (T x columns floats for each
  label row but the first: 1 in feedback; in guidance, whose rows are not known before
  the tables are built, as many of the 2^K - 1 possible as would fit): counted with the
  resident tables.

``python tools/session_memory.py`` measures sessions against this estimate (peak
resident growth in a fresh process, `cfbci.bench.memory_probe`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from calibration_free.config import LearnerConfig
from calibration_free.frames import Frame
from calibration_free.planning import KEPT_INDICATOR_BYTES
from calibration_free.world import GridWorld, World
from session.config import config_world, learner_settings, world_text
from session.plane import is_plane, plane_memory_bytes

_FLOAT = 8
#: The first capacity of `TaskHistory`'s arrays.
_HISTORY_CAPACITY = 64
#: Elements of the temporaries' chunks of the world's optimal table and of the planners
#: (``_TASK_CHUNK_ELEMENTS`` of `calibration_free.world`, ``_CHUNK_ELEMENTS`` of
#: `calibration_free.planning` and `calibration_free.signal_space`).
_CHUNK_ELEMENTS = 1 << 22
#: Per-session memory besides the learner's arrays (Python objects, the recorder, the
#: feature extractor), bytes: a measured floor with margin.
OVERHEAD_BYTES = 2**20
#: The allocator's slack on top of the arrays: the heap grows past the live arrays where
#: freed blocks do not fit the next ones (measured: peak resident growth up to 12 % above
#: the arrays' traced peak, e.g. a 20 x 20 guidance session's fit).
SLACK = 1 / 4
_PER_CLASS_SCATTERS = ("student_t", "gaussian")


@dataclass(frozen=True)
class MemoryEstimate:
    """The estimate's terms, bytes (see the module docstring).

    Attributes
    ----------
    overhead : int
    world_tables : int
        Resident for the whole session.
    world_build : int
        Transient, at the first epoch, before any statistic exists.
    history : int
        Resident from the first epoch on.
    fit, cross_validation, planning : int
        A step's transient peaks (each on top of the history).
    """

    overhead: int
    world_tables: int
    world_build: int
    history: int
    fit: int
    cross_validation: int
    planning: int

    @property
    def step(self) -> int:
        """A step's peak: the history and the largest of its phases."""
        return self.history + max(self.fit, self.cross_validation, self.planning)

    @property
    def arrays(self) -> int:
        """The learner's arrays at their peak: the tables, then the larger of their
        building and a step."""
        return self.world_tables + max(self.world_build, self.step)

    @property
    def total(self) -> int:
        """The upper estimate, bytes: the arrays with the allocator's slack, and the
        overhead."""
        return self.overhead + int(self.arrays * (1 + SLACK))


def estimate(world: World, learner: LearnerConfig, steps: int, n_features: int) -> MemoryEstimate:
    """The memory a session of ``steps`` steps with ``n_features``-long signals commits.

    Parameters
    ----------
    world : World
        The session's world (only its sizes are read, and its transitions' outcomes).
    learner : LearnerConfig
        The session's learner settings (frame, decoder, likelihood, planner, folds).
    steps : int
        Steps of the session (n).
    n_features : int
        Length of the learner's feature vectors (d); 0 when not known yet (the terms in d
        vanish).
    """
    tasks, states, actions = world.n_tasks, world.n_states, world.n_actions
    guidance = learner.frame == "guidance"
    classes = Frame(world, learner.frame).n_classes
    labelled = classes + guidance  # K': guidance's unlabelled signals form a class
    folds, d, n = learner.n_folds, n_features, steps
    sets = folds + 1  # J
    u, u_labelled, v = tasks * classes * d, tasks * labelled * d, tasks * classes * d * d
    padded = n + folds  # the out-of-fold scoring pads the signals to a multiple of F
    scores = tasks * padded * classes  # out-of-fold probabilities, T n K
    per_class = learner.decoder in _PER_CLASS_SCATTERS
    scatters = per_class or learner.likelihood == "bhattacharyya"

    table = tasks * states * actions  # optimal, bool
    world_tables = table + (tasks * states if guidance else 0)

    chunk_tasks = min(tasks, max(1, _CHUNK_ELEMENTS // (states * actions)))
    solved = chunk_tasks * states * actions  # E
    if isinstance(world, GridWorld):  # distances (int64 then int32), then per chunk
        world_build = 4 * _FLOAT * states**2 + 5 * solved
    else:  # rewards, their stack, q, the next values and their sum (x outcomes)
        outcomes = world.transitions.next_states.shape[-1]
        world_build = _FLOAT * (1 + max(4, 2 + 2 * outcomes)) * solved + solved
    if guidance:  # the frame's row table from the optimal guidance actions' bits
        world_build += 3 * tasks * states * classes

    capacity = _HISTORY_CAPACITY
    while capacity < n:
        capacity *= 2
    growing = capacity + capacity // 2  # old and new arrays while doubling
    # Guidance's ambiguous labels split again (any guidance world: the frame's tables are
    # not built at the config): the frame labels kept, and per step the probabilities and
    # split weights of the signals since the last target and the rebuilt fold statistics.
    resplit = guidance and learner.resplit_labels and learner.likelihood == "matching"
    resplit_history = (
        growing * tasks * classes + 4 * n * tasks * classes
        + folds * (tasks * classes + u) + (folds * v if scatters else 0)
    )
    history = _FLOAT * (
        growing * (d + tasks * classes) + 3 * n * classes  # signals, label weights
        + sets * tasks * classes + (sets + 1) * u + folds * (d * d + d)  # fold statistics
        + ((sets + 1) * v if scatters else 0)  # class scatters, and one step's increment
        + (n * tasks * classes if learner.likelihood == "batch" else 0)  # expected labels
        + 3 * tasks * classes + tasks + states  # power sums, log-likelihoods, visits
        + (resplit_history if resplit else 0)
    )

    if per_class:  # means, precisions (+ the whole history's training statistics)
        whole = v + 2 * u
        fit = (1 + 6 * folds) * v + 2 * sets * u
        folded = sets * (v + u + 2 * tasks * classes) + 3 * tasks * classes * padded * d
    else:  # basis, coefficients, intercepts
        whole = d * d + u + tasks * classes
        fit = sets * (3 * u + 4 * u_labelled + 4 * tasks * d + 3 * d * d + 3 * tasks * labelled**2)
        folded = sets * (d * d + u + 2 * tasks * classes)
    if learner.likelihood == "bhattacharyya":  # the whole history's classes' overlaps
        fit = max(fit, 5 * v)
    # LDA's two-class probabilities come from one score difference; the others go
    # through the log-softmax over every class.
    score_arrays = 2 if learner.decoder == "lda" and classes == 2 else 4
    cross_validation = folded + score_arrays * scores

    columns = states * (1 if guidance else actions)
    chunk = min(columns, max(1, _CHUNK_ELEMENTS // tasks))
    if learner.planner in ("uncertainty", "information"):  # kept from step to step
        row_bytes = _FLOAT * tasks * columns
        kept_rows = min(1 if not guidance else 2**classes - 1, KEPT_INDICATOR_BYTES // row_bytes)
        world_tables += kept_rows * row_bytes
    if learner.planner in ("uncertainty", "information", "signal"):
        signals = learner.n_planning_signals
        planner = (
            9 * tasks * chunk  # the row indicator, bool then float
            + _FLOAT * (3 * (signals + 1) + d) * chunk  # totals (or class means) per column
            + _FLOAT * 3 * tasks * (signals + 1) * labelled  # predictions, matches, moments
            + _FLOAT * 8 * states * actions  # reward and value iteration
            + (tasks * columns if learner.planner == "signal" else 0)  # most probable labels
            # the matches normalised over the signals, and their x log x
            + (_FLOAT * 2 * tasks * (signals + 1) * labelled
               if learner.planner == "information" else 0)
        )
    else:
        planner = 0
    planning = _FLOAT * (whole + scores) + planner

    return MemoryEstimate(
        overhead=OVERHEAD_BYTES,
        world_tables=world_tables,
        world_build=world_build,
        history=history,
        fit=_FLOAT * fit,
        cross_validation=_FLOAT * cross_validation,
        planning=planning,
    )


def config_memory_bytes(config: dict[str, Any], n_features: int = 0) -> tuple[int, str]:
    """Upper estimate of the memory a session of a config commits, in bytes, and a short
    description of what it is of (for a rejection's message): every world's estimate in
    one place (`estimate` for the discrete worlds,
    `session.plane.plane_memory_bytes` in the plane).

    Parameters
    ----------
    config : dict
        A config message's fields.
    n_features : int
        Features of the session's signals; 0 when not known yet (at the config).

    Raises
    ------
    ValueError
        As `session.config.learner_settings`.
    """
    what = f"{n_features} features, " if n_features else ""
    if is_plane(config):
        needed = plane_memory_bytes(config, n_features)
        return needed, f"{what}{config['world']} world, {config['steps']} steps"
    world = config_world(config)
    learner = learner_settings(config["learner"], config["frame"])
    needed = estimate(world, learner, config["steps"], n_features).total
    return needed, (
        f"{what}{world_text(world)}, {config['steps']} steps, {learner.decoder} decoder")
