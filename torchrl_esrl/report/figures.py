"""The report's figures: learning curves against TD3 frames and against TD3 + ES frames (mean over
seeds, 95% bootstrap CI of the mean; panels of at most five lines), buffer sizes per run, the TD3
actor vs the ES mean per run, the ratio sweep, hard vs soft overwrite, the aggregate. A row without
TD3 frames (ES alone) is drawn on the TD3-frame axis at the TD3 frames the others have at the same
iteration (``(iteration + 1) x frames_per_iteration``). Which runs a figure holds is read from the
records (a ratio, a TD3 actor, the overwrite mode of the run's config), never from a name."""
from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

import numpy as np

from torchrl_esrl.report.records import PAPER_RATIO, TD3_ACTOR, TD3_ACTOR_SUFFIX, Algorithms, ratio_text, records_overwrites, seeds_text
from torchrl_esrl.report.statistics import interquartile_mean, mean_band
from torchrl_esrl.run.plot import draw_es_vs_td3, pyplot, save_figure

PANEL_WIDTH, PANEL_HEIGHT = 3.3, 2.7  # inches: three panels make a 10-inch row, readable at page width
MAX_COLUMNS, MAX_LINES = 3, 5
BAND = "95% bootstrap CI of the mean over seeds"


def _curve_x(run: dict, axis: str = "td3") -> np.ndarray:
    """x of one run's curve: ``"td3"``, its TD3 frames (a run with none: the TD3 frames the others
    have at the same iteration, ``(iteration + 1) x frames_per_iteration``), or ``"total"``, its
    TD3 + ES frames."""
    if axis == "total":
        return np.array([row["total_frames"] for row in run["metrics"]], dtype=float)
    frames = np.array([row["td3_frames"] for row in run["metrics"]], dtype=float)
    if frames.any():
        return frames
    per_iteration = run["summary"].get("frames_per_iteration", 1)
    return np.array([(row["iteration"] + 1) * per_iteration for row in run["metrics"]], dtype=float)




def _grid(panels: int, columns: int = MAX_COLUMNS, width: float = PANEL_WIDTH, height: float = PANEL_HEIGHT, **kwargs):
    """A figure of ``panels`` axes wrapped at ``columns`` per row; axes beyond ``panels`` hidden."""
    plt = pyplot()
    columns = max(1, min(columns, panels))
    rows = math.ceil(panels / columns)
    fig, axes = plt.subplots(rows, columns, figsize=(width * columns, height * rows), squeeze=False, **kwargs)
    axes = axes.ravel()
    for ax in axes[panels:]:
        ax.set_visible(False)
    return fig, axes




def _curve_groups(runs: list[dict]) -> dict[str, dict[tuple[str, str], list[dict]]]:
    """env -> (algorithm, ratio) -> runs, the rows with a ratio at one ratio only: the paper's when
    it has the most runs or ties (a ratio sweep has its own figure, :func:`plot_ratio_sweep`)."""
    by_env: dict[str, dict[tuple[str, str], list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        if run["metrics"]:
            by_env[run["summary"]["env"]][(run["summary"]["algorithm"], ratio_text(run["summary"]))].append(run)
    out = {}
    for env, by_config in by_env.items():
        ratios = [(len(group), ratio == PAPER_RATIO, ratio) for (algorithm, ratio), group in by_config.items() if ratio]
        main_ratio = max(ratios)[-1] if ratios else ""
        out[env] = {key: group for key, group in by_config.items() if not key[1] or key[1] == main_ratio}
    return out


def curve_panels(keys, with_actor, algorithms: Algorithms) -> list[tuple[str, list[tuple[str, str]]]]:
    """The panels of a learning-curve figure, each (title, rows) with at most ``MAX_LINES`` rows:
    the rows with a TD3 actor inside (``with_actor``); the reference row against the rows without
    one (the baselines); the TD3 actors inside against the baselines that return a TD3 actor. A
    panel with more rows is split."""
    keys = sorted(keys, key=algorithms.row_order)
    variants = [k for k in keys if k in with_actor]
    baselines = [k for k in keys if k not in with_actor]
    reference = [k for k in variants if k[0] == algorithms.reference][:1]
    actors = [(a + TD3_ACTOR_SUFFIX, r) for a, r in variants] + [k for k in baselines if algorithms.info(k[0]).returned == TD3_ACTOR]
    returned = sorted({algorithms.info(a).returned for a, _ in variants})
    alone = [algorithms.label(a) for a, _ in actors if TD3_ACTOR_SUFFIX not in a]
    candidates = [(f"rows with a TD3 actor inside (returned {returned[0] if len(returned) == 1 else 'policy'})", variants if len(variants) > 1 else []),
                  (f"{algorithms.label(reference[0][0])} vs the baselines (returned policy)" if reference else "the baselines (returned policy)", reference + baselines if baselines else []),
                  ("TD3 actors: inside their rows" + (f" and {', '.join(alone)} alone" if alone else ""), actors if len(actors) > 1 and variants else [])]
    panels = []
    for title, rows in candidates:
        for start in range(0, len(rows), MAX_LINES):
            panels.append((title, rows[start:start + MAX_LINES]))
    return panels or [("returned policy", keys[:MAX_LINES])]


def _row_curve(group: list[dict], algorithm: str, axis: str):
    """x (mean over seeds, per iteration) and the return matrix (seeds x iterations) of a row."""
    length = min(len(run["metrics"]) for run in group)
    column = "td3_eval_return" if algorithm.endswith(TD3_ACTOR_SUFFIX) else "eval_return"
    x = np.mean([_curve_x(run, axis)[:length] for run in group], axis=0)
    returns = np.array([[row[column] for row in run["metrics"][:length]] for run in group], dtype=float)
    return x, returns


def _frames_text(value: float, _=None) -> str:
    """Tick label of a frame count: 40k, 2.4M."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(value) >= scale:
            return f"{value / scale:g}{suffix}"
    return f"{value:g}"


def _frame_axis(ax, log: bool) -> None:
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    if log:
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.xaxis.set_major_formatter(FuncFormatter(_frames_text))


def has_td3_actor(run: dict) -> bool:
    """A run that learns a TD3 actor beside the policy it returns (and records its returns)."""
    return "final_td3_actor_return" in run["summary"] or bool(run["metrics"]) and "td3_eval_return" in run["metrics"][0]


def plot_learning_curves(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> list[Path]:
    """``curves_<env>.png``: evaluation return per iteration, one row of panels per group of rows
    (:func:`curve_panels`, at most five lines each), against TD3 frames (left) and against all
    environment frames, TD3 + ES, on a log axis (right); each row's legend under it. Line: mean
    over seeds; band: its 95% bootstrap CI (:func:`mean_band`). A row keeps its colour in every panel."""
    plt = pyplot()
    paths = []
    for env, by_config in sorted(_curve_groups(runs).items()):
        def drawable(key) -> bool:  # a TD3-actor line needs its runs' td3_eval_return
            base = (key[0].partition(TD3_ACTOR_SUFFIX)[0], key[1])
            return TD3_ACTOR_SUFFIX not in key[0] or all("td3_eval_return" in run["metrics"][0] for run in by_config[base])

        with_actor = {key for key, group in by_config.items() if all(map(has_td3_actor, group))}
        panels = [(title, [k for k in rows if drawable(k)]) for title, rows in curve_panels(by_config, with_actor, algorithms)]
        panels = [(title, rows) for title, rows in panels if rows]
        every = sorted({key for _, rows in panels for key in rows}, key=algorithms.row_order)
        without_td3 = dict.fromkeys(algorithms.label(a) for a, r in sorted(by_config, key=algorithms.row_order)
                                    if not any(row["td3_frames"] for run in by_config[(a, r)] for row in run["metrics"]))
        td3_axis = "TD3 frames" + (f" ({', '.join(without_td3)}: at the same iteration)" if without_td3 else "")
        colours = {key: f"C{i % 10}" for i, key in enumerate(every)}
        legend_heights = [0.2 + 0.17 * math.ceil(len(keys) / 2) for _, keys in panels]
        heights = [h for legend in legend_heights for h in (2.7, legend)]
        fig = plt.figure(figsize=(9.2, sum(heights) + 0.5))
        grid = fig.add_gridspec(len(heights), 2, height_ratios=heights)
        for p, (title, keys) in enumerate(panels):
            for column, axis in enumerate(("td3", "total")):
                ax = fig.add_subplot(grid[2 * p, column])
                for key in keys:
                    group = by_config[(key[0].partition(TD3_ACTOR_SUFFIX)[0], key[1])]
                    x, returns = _row_curve(group, key[0], axis)
                    mean, low, high = mean_band(returns)
                    ax.plot(x, mean, marker="o", markersize=2.5, linewidth=1.4, color=colours[key], label=f"{algorithms.label(*key)} ({seeds_text(len(group))})")
                    ax.fill_between(x, low, high, color=colours[key], alpha=0.15, linewidth=0)
                ax.grid(alpha=0.3)
                ax.set_title(title)
                ax.set_ylabel("evaluation return")
                _frame_axis(ax, log=axis == "total")
                ax.set_xlabel("environment frames, TD3 + ES (log)" if axis == "total" else td3_axis)
            legend = fig.add_subplot(grid[2 * p + 1, :])
            legend.axis("off")
            legend.legend(*ax.get_legend_handles_labels(), loc="upper center", ncol=2, frameon=False)
        fig.suptitle(f"{env}: deterministic evaluation per iteration\nline: mean over seeds; band: {BAND}", fontsize=10)
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / f"curves_{env}.png"))
    return paths


def _run_config(run: dict) -> dict:
    """The run's resolved config (``config.yaml`` as recorded, or Hydra's ``.hydra/config.yaml``); {} if none."""
    from omegaconf import OmegaConf

    for path in (run["dir"] / "config.yaml", run["dir"] / ".hydra" / "config.yaml"):
        if path.exists():
            return OmegaConf.to_container(OmegaConf.load(path))
    return {}


def overwrite_mode(run: dict) -> str | None:
    """How the run's TD3 actor overwrites its ES mean (``"hard"``, ``"soft"``): its summary's
    ``overwrite_mode`` if recorded, else its config's ``overwrite.mode``; None if neither says."""
    return run["summary"].get("overwrite_mode") or _run_config(run).get("overwrite", {}).get("mode")


def _file_names(configs: dict, stem) -> dict:
    """A file name per configuration, ``stem(key)``; a name two algorithms would share gets each one's algorithm."""
    names = defaultdict(list)
    for key in configs:
        names[stem(key)].append(key)
    return {key: name + (f"_{key[1]}" if len(keys) > 1 else "") for name, keys in names.items() for key in keys}


BUFFERS = (("good_size", "good"), ("bad_size", "bad"), ("noisy_size", "noisy"))


def plot_buffer_sizes(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> list[Path]:
    """``buffers_<env>.png``: items in the good, bad and noisy buffers at the end of each iteration,
    one panel per buffer and one line per seed, for each three-buffer configuration (one panel row
    each), with K (``buffer.min_size``): with ``buffer.renormalize=false`` (Algorithm 1) TD3 learns
    once every buffer with a share holds K; the title says which rule the runs used."""
    paths = []
    for env, by_config in sorted(_curve_groups(runs).items()):
        configs = [key for key in sorted(by_config, key=algorithms.row_order) if key[1] and all("good_size" in r["metrics"][0] for r in by_config[key])]
        if not configs:
            continue
        fig, axes = _grid(len(configs) * len(BUFFERS), height=2.6)
        rules = set()
        for c, key in enumerate(configs):
            group = sorted(by_config[key], key=lambda r: r["summary"]["seed"])[:MAX_LINES]
            buffer_cfg = _run_config(group[0]).get("buffer", {})
            min_size = buffer_cfg.get("min_size")
            rules.add(buffer_cfg.get("renormalize"))
            for (column, name), ax in zip(BUFFERS, axes[c * len(BUFFERS):]):
                for run in group:
                    iterations = [row["iteration"] + 1 for row in run["metrics"]]
                    ax.plot(iterations, [row[column] for row in run["metrics"]], marker="o", markersize=2.5, linewidth=1.2, label=f"seed {run['summary']['seed']}")
                if min_size:
                    ax.axhline(min_size, color="black", linestyle="--", linewidth=1, label=f"K = {min_size:,}")
                ax.set_yscale("log")
                ax.set_title(f"{algorithms.label(*key)}: {name}")
                ax.set_xlabel("end of iteration")
                ax.set_ylabel("items (log)")
                ax.grid(alpha=0.3, which="both")
            axes[c * len(BUFFERS) + len(BUFFERS) - 1].legend(loc="lower right", framealpha=0.85)  # noisy grows alike in every run: its lower right is free
        rule = {frozenset({False}): "TD3 learns once every buffer with a share holds K",
                frozenset({True}): "TD3 learns from the buffers that hold K, ratio renormalised"}.get(frozenset(rules), "K: the readiness size")
        fig.suptitle(f"{env}: buffer sizes per run ({rule})", fontsize=10)
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / f"buffers_{env}.png"))
    return paths


def _es_vs_td3_stem(key: tuple) -> str:
    env, _, ratio, soft = key
    return f"es_vs_td3_{env}" + ("_soft" if soft else "") + ("" if ratio == PAPER_RATIO else "_ratio_" + ratio.replace(":", "_"))


def plot_es_vs_td3(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> list[Path]:
    """``es_vs_td3_<env>[_soft][_ratio_a_b_c][_<algorithm>].png``, one per configuration with a
    ratio and a TD3 actor (soft: its overwrite mode, :func:`overwrite_mode`; the algorithm only
    where two share the rest): its TD3 actor vs its ES mean per iteration, one panel per run in a
    grid of at most three columns, overwrites marked (the paper's learning-curve figure, run by run)."""
    paths = []
    by_config: dict[tuple[str, str, str, bool], list[dict]] = defaultdict(list)
    for run in runs:
        s = run["summary"]
        if ratio_text(s) and run["metrics"] and "td3_eval_return" in run["metrics"][0]:
            by_config[(s["env"], s["algorithm"], ratio_text(s), overwrite_mode(run) == "soft")].append(run)
    names = _file_names(by_config, _es_vs_td3_stem)
    for (env, algorithm, ratio, soft), group in sorted(by_config.items()):
        group = sorted(group, key=lambda r: r["summary"]["seed"])
        legend_cell = len(group) % MAX_COLUMNS != 0  # a free cell holds the legend
        fig, axes = _grid(len(group) + legend_cell, height=2.5, sharey=True)
        for ax, run in zip(axes, group):
            draw_es_vs_td3(ax, run, algorithms.info(algorithm).returned)
            ax.set_title(f"seed {run['summary']['seed']}")
        for ax in axes[::MAX_COLUMNS]:
            ax.set_ylabel("evaluation return")
        handles, labels = {}, []
        for ax in axes[:len(group)]:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in handles:
                    handles[lab] = h
                    labels.append(lab)
        fig.suptitle(f"{env}: {algorithms.label(algorithm, ratio)}, TD3 actor vs ES mean per run", fontsize=10)
        fig.tight_layout()
        if legend_cell:
            axes[len(group)].axis("off")
            axes[len(group)].legend([handles[lab] for lab in labels], labels, loc="center")
        else:  # under the grid (the saved image grows to hold it)
            fig.legend([handles[lab] for lab in labels], labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=len(labels), frameon=False)
        paths.append(save_figure(fig, out_dir / f"{names[(env, algorithm, ratio, soft)]}.png"))
    return paths


def plot_ratio_sweep(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> list[Path]:
    """``ratio_sweep_<env>[_soft][_<algorithm>].png``, per env and algorithm (and overwrite mode)
    with runs at 2+ ratios: final return vs ratio, of the returned policy and of the TD3 actor (the
    policy the ratio acts on directly): mean ± std, seeds as dots."""
    plt = pyplot()

    paths = []
    by_config: dict[tuple[str, str, bool], dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        s = run["summary"]
        if ratio_text(s):
            by_config[(s["env"], s["algorithm"], overwrite_mode(run) == "soft")][ratio_text(s)].append(s)
    by_config = {key: by_ratio for key, by_ratio in by_config.items() if len(by_ratio) >= 2}
    names = _file_names(by_config, lambda key: f"ratio_sweep_{key[0]}" + ("_soft" if key[2] else ""))
    for (env, algorithm, soft), by_ratio in sorted(by_config.items()):
        series = (("final_return", f"{algorithms.info(algorithm).returned} (returned)", "o", -0.12), ("final_td3_actor_return", TD3_ACTOR, "s", 0.12))
        ratios = sorted(by_ratio)
        fig, ax = plt.subplots(figsize=(max(5.5, 1.6 * len(ratios)), 4))
        for color, (key, name, marker, shift) in enumerate(series):
            for i, ratio in enumerate(ratios):
                values = np.array([s[key] for s in by_ratio[ratio] if key in s], dtype=float)
                if not len(values):
                    continue
                std = values.std(ddof=1) if len(values) > 1 else 0.0
                ax.errorbar(i + shift, values.mean(), yerr=std, fmt=marker, capsize=4, color=f"C{color}", label=name if i == 0 else None)
                ax.scatter(np.full(len(values), i + shift + 0.05), values, s=10, color=f"C{color}", alpha=0.5)
        ax.set_xticks(range(len(ratios)), [f"{r}\n({seeds_text(len(by_ratio[r]))})" for r in ratios], fontsize=8)
        ax.set_xlabel("buffer ratio good:bad:noisy")
        ax.set_ylabel("final evaluation return")
        named = names[(env, algorithm, soft)].endswith(f"_{algorithm}")  # another algorithm has a sweep here too
        ax.set_title(f"{env}: " + (f"{algorithms.label(algorithm)}, " if named or soft else "") + "ratio sweep (mean ± std; dots: seeds)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="best")
        paths.append(save_figure(fig, out_dir / f"{names[(env, algorithm, soft)]}.png"))
    return paths


def plot_hard_vs_soft(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> list[Path]:
    """Per env with both: the rows at the paper's ratio whose runs record overwrites, those with the
    hard overwrite (Algorithm 1) against those with the soft one (Section 5; the mode:
    :func:`overwrite_mode`, hard where none is recorded). Left: the returned policy's evaluation
    return, mean over seeds with its 95% bootstrap CI; right: final return per seed, with the
    number of overwrites each run made next to its dot, and the IQM."""
    paths = []
    by_env: dict[str, dict[tuple[bool, str], list[dict]]] = defaultdict(lambda: defaultdict(list))
    for run in runs:
        s = run["summary"]
        if ratio_text(s) == PAPER_RATIO and run["metrics"] and records_overwrites(run):
            by_env[s["env"]][(overwrite_mode(run) == "soft", s["algorithm"])].append(run)
    for env, by_mode in sorted(by_env.items()):
        rows = sorted(by_mode, key=lambda key: (key[0], algorithms.row_order((key[1], PAPER_RATIO))))
        modes = [soft for soft, _ in rows]
        if len(set(modes)) < 2:
            continue
        plt = pyplot()
        fig, (curves, finals) = plt.subplots(1, 2, figsize=(9, 3.4), gridspec_kw={"width_ratios": [2, 1]})
        for i, (soft, algorithm) in enumerate(rows):
            group = by_mode[(soft, algorithm)]
            x, returns = _row_curve(group, algorithm, "td3")
            mean, low, high = mean_band(returns)
            curves.plot(x, mean, marker="o", markersize=2.5, color=f"C{i}", label=f"{algorithms.label(algorithm)} ({seeds_text(len(group))})")
            curves.fill_between(x, low, high, color=f"C{i}", alpha=0.15, linewidth=0)
            values = [run["summary"]["final_return"] for run in group]
            spread = i + np.linspace(-0.15, 0.15, len(values)) if len(values) > 1 else np.full(1, float(i))  # equal returns stay apart
            finals.scatter(spread, values, color=f"C{i}", s=18)
            for x, value, run in zip(spread, values, group):
                finals.annotate(str(run["summary"].get("overwrites", "")), (x, value), textcoords="offset points", xytext=(4, -3), fontsize=7)
            finals.hlines(interquartile_mean(values), i - 0.2, i + 0.2, color=f"C{i}")
        curves.set_xlabel("TD3 frames")
        returned = sorted({algorithms.info(algorithm).returned for _, algorithm in rows})
        curves.set_ylabel(f"evaluation return (returned {returned[0] if len(returned) == 1 else 'policy'})")
        curves.set_title(f"line: mean over seeds; band: {BAND}", fontsize=8.5)
        curves.grid(alpha=0.3)
        curves.legend(loc="best", framealpha=0.85)
        ticks = ["soft" if soft else "hard" for soft in modes] if len(rows) == 2 else [algorithms.label(a) for _, a in rows]
        finals.set_xticks(range(len(rows)), ticks)
        finals.set_xlim(-0.6, len(rows) - 0.4)
        finals.set_ylabel("final return")
        finals.set_title("seeds; line: IQM; numbers: overwrites", fontsize=8.5)
        finals.grid(alpha=0.3)
        fig.suptitle(f"{env}: hard vs soft overwrite, {', '.join(algorithms.label(a) for soft, a in rows if not soft)} {PAPER_RATIO}", fontsize=10)
        fig.tight_layout()
        paths.append(save_figure(fig, out_dir / f"hard_vs_soft_{env}.png"))
    return paths


def plot_aggregate(rows: list[dict], tasks: list[str], out_dir: Path, algorithms: Algorithms) -> list[Path]:
    """``aggregate.png`` (2+ tasks): per row, the aggregate IQM of the normalised scores with its
    95% stratified-bootstrap CI (left), and P(reference > row) with its CI (right)."""
    if not rows:
        return []
    plt = pyplot()
    names = [algorithms.label(r["algorithm"], r["ratio"]) for r in rows]
    y = np.arange(len(rows))[::-1]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 0.45 * len(rows) + 1.4), sharey=True)
    for ax, key, title in ((left, "iqm", "aggregate IQM, normalised score"), (right, "probability", f"P({algorithms.label(algorithms.reference or '')} {PAPER_RATIO} > row)")):
        for yi, r in zip(y, rows):
            if math.isnan(r[key]):
                continue
            low, high = r[f"{key}_ci_low"], r[f"{key}_ci_high"]
            if not math.isnan(low):
                ax.hlines(yi, low, high, color="C0", linewidth=3, alpha=0.5)
            ax.plot(r[key], yi, "o", color="C0")
        ax.set_title(title)
        ax.grid(alpha=0.3, axis="x")
    left.axvline(0, color="grey", linestyle=":", linewidth=1)
    left.axvline(1, color="grey", linestyle="--", linewidth=1)
    left.set_xlabel(f"0: initial policy, 1: {algorithms.label(algorithms.normalise_by or '')}'s mean")
    right.axvline(0.5, color="grey", linestyle="--", linewidth=1)
    right.set_xlim(-0.02, 1.02)
    right.set_xlabel("0.5: no difference")
    left.set_yticks(y, names)
    fig.suptitle(f"Across {len(tasks)} tasks ({', '.join(tasks)}); bars: 95% stratified-bootstrap CI", fontsize=10)
    fig.tight_layout()
    return [save_figure(fig, out_dir / "aggregate.png")]


