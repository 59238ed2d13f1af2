"""What ``cfbci bench soak`` prints and plots of its report
(`cfbci.bench.soak.bench_soak`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table


def print_soak(report: dict[str, Any], console: Console) -> None:
    """The long session's windows, its growth, and the short sessions' leak figures."""
    long, short = report["long"], report["short"]
    table = Table(title=f"bench soak: one session of {long['steps']} steps, "
                        f"T = {report['grid'] ** 2} (service process)")
    for column in ("step", "RSS MB", "growth MB", "end to end median / p99 ms",
                   "learner update median / p99 ms", "reference ms", "update / reference"):
        table.add_column(column, justify="right")
    for row in long["windows"]:
        table.add_row(
            str(row["step"]), f"{row['rss_mb']:.1f}", f"{row['rss_growth_mb']:+.1f}",
            f"{row['end_to_end_median_ms']:.2f} / {row['end_to_end_p99_ms']:.2f}",
            f"{row['update_median_ms']:.2f} / {row['update_p99_ms']:.2f}",
            f"{row['reference_ms']:.2f}", f"{row['update_median_ms'] / row['reference_ms']:.2f}",
        )
    console.print(table)
    console.print(
        "reference: the median of 30 steps of the same learner offline in this process, at "
        "a short history, taken at the window's end (the machine's speed then)", soft_wrap=True,
    )
    growth, recorder = long["growth"], long["recorder"]
    first, second = growth["halves"]["first"], growth["halves"]["second"]
    console.print(
        f"slopes over steps {first[0]}-{first[1]} / {second[0]}-{second[1]}: RSS "
        f"{growth['rss_kb_per_step']['first']:.2f} / {growth['rss_kb_per_step']['second']:.2f} "
        "KB per step; end to end "
        f"{growth['end_to_end_ms_per_1000_steps']['first']:+.2f} / "
        f"{growth['end_to_end_ms_per_1000_steps']['second']:+.2f} ms per 1000 steps; learner "
        f"{growth['update_ms_per_1000_steps']['first']:+.2f} / "
        f"{growth['update_ms_per_1000_steps']['second']:+.2f} ms per 1000 steps",
        soft_wrap=True,
    )
    learner = long["learner"]
    console.print(
        f"the history's own memory, measured in this process: the recorder keeps "
        f"{recorder['bytes_per_message']:.0f} bytes per message until the file is closed "
        f"(chunk indexes), {recorder['messages_per_step']:.2f} messages per step: "
        f"{recorder['kb_per_step']:.2f} KB per step; the learner (offline, d = "
        f"{learner['n_features']}) keeps {learner['kb_per_step']:.2f} KB per step, and its "
        f"peak within a step grows by {learner['peak_kb_per_step']:.2f} KB per step; "
        f"recorder and learner's peak together "
        f"{recorder['kb_per_step'] + learner['peak_kb_per_step']:.2f} KB per step",
        soft_wrap=True,
    )
    console.print(
        f"{short['sessions']} short sessions of {short['steps']} steps: service RSS "
        f"{short['rss_before_mb']:.1f} MB before, {short['rss_mb'][0]:.1f} MB after the first, "
        f"{short['rss_mb'][-1]:.1f} MB after the last: {short['growth_mb']:+.2f} MB, "
        f"{short['per_session_kb']:+.1f} KB per session (median)", soft_wrap=True,
    )


def plot_soak(report: dict[str, Any], path: Path) -> None:
    """Three panels: RSS and per-step times against step, RSS against short session."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    long, short = report["long"], report["short"]
    figure = Figure(figsize=(13, 4), layout="constrained")
    memory, times, sessions = figure.subplots(1, 3)
    steps = np.arange(1, long["steps"] + 1)
    memory.plot(steps, long["rss_mb"], color="tab:blue")
    memory.set(xlabel="step", ylabel="service RSS (MB)",
               title=f"resident memory, one {long['steps']}-step session")
    epochs = np.arange(1, long["steps"])
    for key, label, colour in (("end_to_end_ms", "end to end", "tab:orange"),
                               ("update_ms", "learner update", "tab:green")):
        values = np.asarray(long[key])
        times.plot(epochs, values, ",", color=colour, alpha=0.3)
        window = min(101, len(values))
        median = np.array([np.median(values[max(0, i - window // 2): i + window // 2 + 1])
                           for i in range(len(values))])
        times.plot(epochs, median, color=colour, label=f"{label} (running median)")
    ends = [row["step"] for row in long["windows"]]
    times.plot(ends, [row["reference_ms"] for row in long["windows"]], "k^", markersize=4,
               label="reference (offline, short history)")
    times.set(xlabel="step", ylabel="ms per step", title="per-step time",
              ylim=(0, 2 * np.percentile(long["end_to_end_ms"], 99)))
    times.legend(loc="upper left")
    sessions.plot(np.arange(1, short["sessions"] + 1), short["rss_mb"], "o-", markersize=2)
    sessions.set(xlabel="short session", ylabel="service RSS after it (MB)",
                 title=f"{short['sessions']} sessions of {short['steps']} steps\n"
                       f"(RSS before the first: {short['rss_before_mb']:.0f} MB)")
    figure.savefig(path, dpi=120)
