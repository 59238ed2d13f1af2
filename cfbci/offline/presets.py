"""Named settings of the thesis's experiments: ``cfbci simulate --preset NAME``.

A preset gives defaults to ``cfbci simulate``'s options and learner settings (``--set``),
with the settings ``../shared/docs/method-extensions.md`` gives for that experiment;
options given explicitly on the command line override it (a ``--set key=value`` overrides
the preset's value of that key). ``cfbci simulate --list-presets`` lists them. A preset's
shrinkage is two settings, ``shrinkage`` and ``first_target_shrinkage``: ``--set`` both to
change it throughout.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Preset:
    """The settings of one experiment.

    Attributes
    ----------
    name : str
    summary : str
        The experiment, where it comes from, and what the user must still give.
    options : dict
        Defaults of ``cfbci simulate`` options, by argparse destination (``seeds``,
        ``steps``, ``world``, ``synthetic``...).
    learner : dict
        Learner settings (`calibration_free.config.LearnerConfig` fields).
    dataset : str or None
        The dataset the experiment needs when it does not run on synthetic data
        (``--dataset`` must then be given).
    """

    name: str
    summary: str
    options: dict[str, Any]
    learner: dict[str, Any] = field(default_factory=dict)
    dataset: str | None = None

    def defaults(self) -> dict[str, Any]:
        """The argparse defaults this preset sets (``set``: its learner settings first)."""
        settings = [f"{key}={json.dumps(value)}" for key, value in self.learner.items()]
        return {**self.options, "set": settings}

    def describe(self) -> str:
        """One paragraph: the summary and every setting."""
        options = " ".join(f"--{k.replace('_', '-')} {v}" for k, v in self.options.items())
        learner = " ".join(f"{k}={json.dumps(v)}" for k, v in self.learner.items())
        needs = f"; needs --dataset {self.dataset}" if self.dataset else ""
        return f"{self.name}: {self.summary}{needs}\n    {options}\n    learner: {learner}"


#: The thesis's own choices shared by the experiments of chapters 4-7: no ErrP power prior
#: (the signals are not ErrPs), none of the project's novelty bonus nor of its stricter first
#: target, planning discount 0.95.
_THESIS = {"power_prior": False, "novelty_bonus": 0.0, "first_target_signals": 0,
           "discount": 0.95}
#: The thesis's shrinkage, 0.5, throughout: none of the project's heavier one before the first
#: target (``first_target_shrinkage``).
_THESIS_SHRINKAGE = {"shrinkage": 0.5, "first_target_shrinkage": 0.5}

PRESETS: dict[str, Preset] = {
    preset.name: preset
    for preset in (
        Preset(
            "frame-hypotheses",
            "thesis §7.6 (method-extensions §4): (task, frame) pairs on the line world, the "
            "teacher's frame alternating with the seed; 200 runs of 200 steps, random "
            "actions, the thesis code's Student-t decoder (total count), eps 0.01, 12 "
            "initial steps",
            {"world": "line", "frame": "hypotheses", "seeds": 200, "steps": 200,
             "planner": "random"},
            {"decoder": "student_t", "student_t_counts": "total", **_THESIS_SHRINKAGE,
             "eps": 0.01, "warmup_steps": 12},
            dataset='"$(cfbci datasets path finger)" (after `cfbci datasets fetch finger`)',
        ),
        Preset(
            "world-properties",
            "thesis §7.2 (method-extensions §7.2): 2-D Gaussian signals of accuracy 0.95, "
            "simple matching, normalised likelihood > 0.9, Gaussian decoder with shrinkage "
            "0.5, eps 0.01, 10 initial random steps, uncertainty planning; 50 runs of 100 "
            "steps; choose the world with --world/--grid (5 x 5, 25 x 25, pick-and-place); "
            "--set goal_pull=1 adds the progress toward the likely goals that the study "
            "recommends",
            {"synthetic": "gaussian", "dims": 2, "synthetic_accuracy": 0.95, "seeds": 50,
             "steps": 100, "frame": "feedback", "planner": "uncertainty"},
            {"likelihood": "simple", "confidence": "normalised", "beta": 0.9,
             "decoder": "gaussian", **_THESIS_SHRINKAGE, "eps": 0.01, "warmup_steps": 10,
             **_THESIS},
        ),
        Preset(
            "simple-vs-matching",
            "thesis §7.1 (method-extensions §7.3): 5 x 5 grid, feedback, 2-D Gaussian "
            "signals of accuracy 0.65, Student-t decoder with shrinkage 0.5, learner eps "
            "0.1, pairwise W > 0.9, uncertainty planning, 12 initial steps; 100 runs of 500 "
            "steps; simple matching (--set likelihood=matching for the other arm)",
            {"synthetic": "gaussian", "dims": 2, "synthetic_accuracy": 0.65, "seeds": 100,
             "steps": 500, "grid": 5, "frame": "feedback", "planner": "uncertainty"},
            {"likelihood": "simple", "decoder": "student_t", **_THESIS_SHRINKAGE, "eps": 0.1,
             "confidence": "pairwise", "beta": 0.9, "warmup_steps": 12, **_THESIS},
        ),
        Preset(
            "pick-and-place-speech",
            "thesis chapter 4 (method-extensions §6): pick-and-place with spoken words "
            "(feedback; --frame guidance for the 4-word frame), epsilon-greedy 0.1, batch "
            "matching without cross-validation, Gaussian decoder, normalised likelihood; one "
            "taught task per run (no target declared: the figure is its normalised "
            "likelihood); 20 runs of 200 steps",
            {"world": "pick-and-place", "frame": "feedback", "seeds": 20, "steps": 200,
             "planner": "epsilon-greedy"},
            {"epsilon": 0.1, "likelihood": "batch", "decoder": "gaussian", **_THESIS_SHRINKAGE,
             "confidence": "normalised", "beta": 0.9, "eps": 0.1, "warmup_steps": 0,
             "declare_targets": False, **_THESIS},
            dataset="FILE.npz from `cfbci datasets speech --out FILE.npz`",
        ),
    )
}


def preset(name: str) -> Preset:
    """The preset called ``name``; a ValueError listing the known ones otherwise."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]
