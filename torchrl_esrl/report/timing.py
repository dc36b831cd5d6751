"""What a run's records say of its time: the attempts its command took, the holds, and both net
of the holds.

- ``pieces.txt`` (``scripts/paper_run.sh``) and ``timing.txt`` (``scripts/multibuffer_experiments.sh``):
  one line per attempt of the run's command, with its seconds, commit and ending; a piece also its
  start (UTC) and peak memory, a recent timing line its start; both the 1-minute load average's
  mean and largest value over the attempt, and the processor it ran on (``scripts/processor.sh``),
  where recorded.
- ``pauses.txt`` (``scripts/pause_runs.sh``): when the run was held (SIGSTOP) and let go, UTC.
  Every hold lies inside an attempt (only a running process is held), so the attempts' seconds net
  of the holds are their sum less the held seconds.
- The training clock (``summary.json``'s ``wall_time_s``, carried across a resume) counts a hold
  only when the work around it was kept: a hold in work a killed attempt lost, and redone, is in
  the attempts' seconds but not in the clock. A hold is placed in the clock (``counted``) when the
  records show it: the run's log (``run.log``, the recipe's ``<recipe>.log``: its times, local, read
  as UTC like the machines' own) has a finished iteration after it in the same attempt; or its
  attempt ran to the end (exit 0); or it ended at least ``slack`` seconds before its attempt was
  killed, ``slack`` being the attempts' seconds less the clock, which bounds the work any one
  attempt lost (start-up, seconds before the clock runs, is taken as hold-free). A hold none of
  these place leaves the net clock a range.
- The attempts' seconds below the training clock mean an attempt is missing from the record:
  the run took at least its clock.
"""
from __future__ import annotations

import re
from collections import defaultdict
from dataclasses import dataclass, field
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from torchrl_esrl.report.records import Algorithms, ratio_text

PIECE = re.compile(r"piece (\d+) commit (\S+) start (\S+)(?: cpu (.+?))? seconds (\d+) peak_rss_mib (\d+)(?: load_mean (\S+) load_max (\S+))? (.+)")
TIMING = re.compile(r"exit (\S+) after (\d+) s(?: on commit (\S+))?(?: started (\S+))?(?: load_mean (\S+) load_max (\S+))?(?: cpu (.+?))?(?: \((?!started over)[^)]*\))?( \(started over\))?$")
HOLD = re.compile(r"(pause|resume) (\S+)")
LOG = re.compile(r"\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d)[,.]\d+\] (started|resumed|iteration \d+/\d+ |finished)")
END_SLACK_S = 3  # an attempt's seconds are whole and sampled every 2 s: a hold may end this far past them


def utc(text: str) -> datetime:
    """A record's time: ``2026-12-04T05:09:33Z`` (the scripts) or ``2026-12-04 05:09:33`` (the run's log)."""
    return datetime.fromisoformat(text.replace("Z", "").replace(" ", "T")).replace(tzinfo=timezone.utc)


@dataclass(frozen=True)
class Attempt:
    """One attempt of a run's command: a piece of ``pieces.txt`` or a line of ``timing.txt``."""

    seconds: int
    ending: str  # "exit 0", "exit 143", "killed"
    commit: str = ""
    start: datetime | None = None
    started_over: bool = False  # timing.txt: an attempt whose work was thrown away, the run started over
    peak_rss_mib: int | None = None
    load: tuple[float, float] | None = None  # the 1-minute load average over the attempt: mean, largest
    cpu: str = ""  # the processor it ran on (scripts/processor.sh: "family 25 model 17 AMD EPYC"); "" where not recorded

    @property
    def end(self) -> datetime | None:
        return None if self.start is None else self.start + timedelta(seconds=self.seconds)

    @property
    def finished(self) -> bool:
        return self.ending == "exit 0"


@dataclass(frozen=True)
class Hold:
    """One hold of ``pauses.txt``; ``resume`` None: the record has no resume after the pause."""

    pause: datetime
    resume: datetime | None

    @property
    def seconds(self) -> float:
        return (self.resume - self.pause).total_seconds() if self.resume is not None else 0.0


def read_attempts(run_dir: Path) -> list[Attempt]:
    """The run's attempts, from ``pieces.txt`` or else ``timing.txt``; none when it has neither."""
    if (run_dir / "pieces.txt").exists():
        found = [PIECE.fullmatch(line.strip()) for line in (run_dir / "pieces.txt").read_text().splitlines()]
        return [Attempt(int(m[5]), m[9], m[2], utc(m[3]), peak_rss_mib=int(m[6]), load=(float(m[7]), float(m[8])) if m[7] else None, cpu=m[4] or "")
                for m in found if m]
    if (run_dir / "timing.txt").exists():
        found = [TIMING.search(line.rstrip()) for line in (run_dir / "timing.txt").read_text().splitlines()]
        return [Attempt(int(m[2]), f"exit {m[1]}", m[3] or "", utc(m[4]) if m[4] else None, bool(m[8]), load=(float(m[5]), float(m[6])) if m[5] else None,
                        cpu=m[7] or "") for m in found if m]
    return []


def read_holds(run_dir: Path) -> list[Hold]:
    """The holds of ``pauses.txt``: each pause with the first resume after it (a pause while held
    extends the hold; a resume while not held is ignored)."""
    if not (run_dir / "pauses.txt").exists():
        return []
    holds, paused = [], None
    for m in filter(None, (HOLD.match(line.strip()) for line in (run_dir / "pauses.txt").read_text().splitlines())):
        if m[1] == "pause" and paused is None:
            paused = utc(m[2])
        elif m[1] == "resume" and paused is not None:
            holds.append(Hold(paused, utc(m[2])))
            paused = None
    return holds + ([Hold(paused, None)] if paused is not None else [])


def read_log(run_dir: Path) -> list[list[tuple[datetime, str]]]:
    """The run's log (``run.log``) as attempts: from each started or resumed line, the times of the
    lines that follow it, each with its kind (``iteration``, ``finished``)."""
    path = run_dir / "run.log"
    if not path.exists():
        return []
    segments: list[list[tuple[datetime, str]]] = []
    for m in filter(None, (LOG.match(line) for line in path.read_text().splitlines())):
        kind = m[2].split()[0]
        if kind in ("started", "resumed"):
            segments.append([(utc(m[1]), kind)])
        elif segments:
            segments[-1].append((utc(m[1]), kind))
    return segments


@dataclass
class RunTime:
    """A run's time from its records (:func:`run_time`). ``seconds``: the attempts' sum;
    ``clock``: the training clock; ``held``: every resumed hold's seconds; ``counted``: those of
    the holds placed in the clock; ``open_holds``: holds without a resume in the record."""

    attempts: list[Attempt]
    holds: list[Hold]
    clock: float | None
    counted: float = 0.0
    open_holds: int = 0
    per_attempt: list[float] = field(default_factory=list)  # held seconds inside each attempt with a start

    @property
    def seconds(self) -> int:
        return sum(a.seconds for a in self.attempts)

    @property
    def held(self) -> float:
        return sum(h.seconds for h in self.holds)

    @property
    def missing(self) -> bool:
        """The attempts add up to less than the training clock: one is missing from the record."""
        return self.clock is not None and self.seconds + END_SLACK_S < self.clock

    @property
    def seconds_net(self) -> float:
        """The attempts' seconds net of the holds; at least the clock (net) where an attempt is missing."""
        return max(self.seconds, self.clock or 0.0) - self.held if self.missing else self.seconds - self.held

    @property
    def clock_net(self) -> tuple[float, float] | None:
        """The training clock net of the holds: (less every hold, less the holds placed in it)."""
        return None if self.clock is None else (self.clock - self.held, self.clock - self.counted)


def _containing(attempts: list[Attempt], hold: Hold) -> Attempt | None:
    return next((a for a in attempts if a.start is not None and a.start <= hold.pause and hold.resume <= a.end + timedelta(seconds=END_SLACK_S)), None)


def _in_logged_work(segments, hold: Hold) -> bool:
    """The run's log shows the clock ran on past the hold: an iteration or the finish after it, in its attempt."""
    for segment in segments:
        if segment[0][0] <= hold.pause and any(time >= hold.resume for time, kind in segment[1:]):
            return True
    return False


def run_time(run: dict) -> RunTime:
    """:class:`RunTime` of a run of :func:`~torchrl_esrl.report.records.find_runs`: its attempts,
    holds, clock, and the holds placed in the clock (the module's rules)."""
    run_dir = Path(run["dir"])
    attempts, holds = read_attempts(run_dir), read_holds(run_dir)
    clock = run["summary"].get("wall_time_s")
    resumed = [h for h in holds if h.resume is not None]
    result = RunTime(attempts, resumed, clock, open_holds=len(holds) - len(resumed))
    if clock is None:
        return result
    segments, slack = read_log(run_dir), max(0.0, result.seconds - clock)
    only = attempts[0] if len(attempts) == 1 and attempts[0].finished else None
    for hold in resumed:
        attempt = _containing(attempts, hold)
        placed = (_in_logged_work(segments, hold) or only is not None
                  or attempt is not None and (attempt.finished or (attempt.end - hold.resume).total_seconds() >= slack))
        result.counted += hold.seconds if placed else 0.0
    result.per_attempt = [sum(h.seconds for h in resumed if _containing([a], h) is not None) for a in attempts]
    return result


def held_text(time: RunTime) -> str:
    """The holds in words: ``5,478 s in 18 holds``."""
    count = len(time.holds)
    return f"{time.held:,.0f} s in {count} hold{'s' if count != 1 else ''}" + (f" and {time.open_holds} pause(s) without a resume" if time.open_holds else "")


def clock_text(time: RunTime) -> str:
    """The training clock and its net of holds in words."""
    low, high = time.clock_net
    if not time.holds:
        return f"training clock {time.clock:,.0f} s"
    if low == high:
        return f"training clock {time.clock:,.0f} s, every hold within it: {high:,.0f} s net of holds"
    return (f"training clock {time.clock:,.0f} s; {time.counted:,.0f} s of the holds are placed within it, the other {time.held - time.counted:,.0f} s "
            f"fell where the records cannot say whether the clock counted them (work a killed attempt may have lost): {low:,.0f}-{high:,.0f} s net of holds")


def net_minutes_text(time: RunTime) -> str:
    """The training clock net of holds, in minutes (a range where holds are unplaced), for a table cell."""
    if time.clock_net is None:
        return "-"
    low, high = (value / 60 for value in time.clock_net)
    return f"{high:.1f}" if abs(high - low) < 0.05 else f"{low:.1f}-{high:.1f}"


def load_text(attempts: list[Attempt]) -> str:
    """The 1-minute load average over the attempts that record it: their means (a range) and the
    largest value, with how many attempts record one: ``2.11-2.43 / 3.19 (2 of 2)``."""
    loads = [a.load for a in attempts if a.load]
    if not loads:
        return "-"
    low, high = min(mean for mean, _ in loads), max(mean for mean, _ in loads)
    means = f"{low:.2f}" if low == high else f"{low:.2f}-{high:.2f}"
    return f"{means} / {max(largest for _, largest in loads):.2f} ({len(loads)} of {len(attempts)})"


def processors_text(attempts: list[Attempt]) -> str:
    """The processors the attempts ran on, each once, and how many attempts do not record one:
    ``family 25 model 17 AMD EPYC; not recorded for 1 of 2``."""
    named = list(dict.fromkeys(a.cpu for a in attempts if a.cpu))
    unnamed = sum(not a.cpu for a in attempts)
    if not named:
        return "-"
    return "; ".join(named) + (f"; not recorded for {unnamed} of {len(attempts)}" if unnamed else "")


def per_run_table(per_run: list[tuple[str, str, int, RunTime]]) -> list[str]:
    """One row per run: its attempts and how they ended, its command seconds net of holds, the held
    seconds, the load it ran at, the processors and the commits it ran on."""
    lines = ["| env | row | seed | attempts: endings | seconds net of holds | held (s) | load average over its attempts: means / largest (attempts recording it) | processors | commits |",
             "|---|---|---:|---|---:|---:|---|---|---|"]
    for env, name, seed, time in per_run:
        endings = ", ".join(a.ending.removeprefix("exit ") + (" (started over)" if a.started_over else "") for a in time.attempts)
        commits = ", ".join(dict.fromkeys(a.commit[:7] for a in time.attempts if a.commit)) or "-"
        lines.append(f"| {env} | {name} | {seed} | {len(time.attempts)}: {endings} | {time.seconds_net:,.0f} | {time.held:,.0f} | "
                     f"{load_text(time.attempts)} | {processors_text(time.attempts)} | {commits} |")
    return lines


def write_timing(runs: list[dict], out_dir: Path, algorithms: Algorithms) -> Path | None:
    """``timing.md``: per row of ``timing.txt`` runs, their command seconds net of holds (median,
    smallest, largest, total) with the held seconds beside, then each run's attempts, seconds, load
    and commits; per ``pieces.txt`` run, its pieces; a line for every run held or with an attempt
    missing from its record."""
    per_run: list[tuple[str, str, int, RunTime]] = []
    pieces, notes = [], []
    for run in runs:
        s = run["summary"]
        key, time = (s["env"], algorithms.label(s["algorithm"], ratio_text(s))), run_time(run)
        if not time.attempts:
            continue
        if (run["dir"] / "pieces.txt").exists():
            pieces.append((key, s["seed"], time))
            continue
        per_run.append((*key, s["seed"], time))
        what = f"{key[0]}, {key[1]}, seed {s['seed']}"
        if time.missing:
            notes.append(f"- {what}: `timing.txt` holds {time.seconds:,} s in {len(time.attempts)} attempt{'s' if len(time.attempts) != 1 else ''}, less than its "
                         f"training clock of {time.clock:,.0f} s: an attempt is missing from the record, and the run took at least its clock.")
        if time.holds or time.open_holds:
            notes.append(f"- {what}: held {held_text(time)} (`pauses.txt`); {time.seconds:,} s of commands, {time.seconds_net:,.0f} s net of holds; {clock_text(time)}.")
    if not per_run and not pieces:
        return None
    per_row: dict[tuple[str, str], list[RunTime]] = defaultdict(list)
    for env, name, _, time in per_run:
        per_row[env, name].append(time)
    lines = []
    if per_run:
        lines += ["| env | row | runs | median (s) | smallest (s) | largest (s) | total (s) | held (s) | runs held | runs with an attempt missing |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for (env, name), times in sorted(per_row.items()):
            net = [t.seconds_net for t in times]
            lines.append(f"| {env} | {name} | {len(times)} | {np.median(net):.0f} | {min(net):.0f} | {max(net):.0f} | {sum(net):.0f} | "
                         f"{sum(t.held for t in times):.0f} | {sum(bool(t.holds) for t in times)} | {sum(t.missing for t in times)} |")
        every = [time for *_, time in per_run]
        lines += ["", f"{len(every)} runs, {sum(t.seconds_net for t in every):,.0f} s of commands in all net of holds, {sum(t.held for t in every):,.0f} s held "
                  "(`timing.txt`: each attempt's command seconds, summed per run; `pauses.txt`: the holds, subtracted; a run whose attempts add up to less "
                  "than its training clock counts its clock, a lower bound). Each run:", "", *per_run_table(sorted(per_run, key=lambda item: item[:3])),
                  *([""] + notes if notes else []), ""]
    for (env, name), seed, time in pieces:
        loads, cpus = any(a.load for a in time.attempts), any(a.cpu for a in time.attempts)
        lines += [f"{env}, {name}, seed {seed} (`pieces.txt`):", "",
                  "| piece | commit | start | seconds | held (s) | peak resident memory (MiB) |" + (" load average, mean / largest |" if loads else "")
                  + (" processor |" if cpus else "") + " ending |",
                  "|---:|---|---|---:|---:|---:|" + ("---|" if loads else "") + ("---|" if cpus else "") + "---|"]
        for i, (a, held) in enumerate(zip(time.attempts, time.per_attempt)):
            load = f" {a.load[0]:.2f} / {a.load[1]:.2f} |" if a.load else (" - |" if loads else "")
            cpu = f" {a.cpu or '-'} |" if cpus else ""
            lines.append(f"| {i} | {a.commit[:7]} | {a.start:%Y-%m-%dT%H:%M:%SZ} | {a.seconds} | {held:.0f} | {a.peak_rss_mib} |{load}{cpu} {a.ending} |")
        count = len(time.attempts)
        text = f"{time.seconds:,} s in {count} piece{'s' if count != 1 else ''}"
        if time.holds or time.open_holds:
            text += f"; held {held_text(time)} (`pauses.txt`): {time.seconds_net:,.0f} s net of holds; {clock_text(time)}"
        lines += ["", text + ".", ""]
    path = out_dir / "timing.md"
    path.write_text("\n".join(lines))
    return path
