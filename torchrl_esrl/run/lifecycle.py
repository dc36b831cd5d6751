"""One run lifecycle for every recipe.

``main = recipe_main(train, config_name=..., algorithm=..., holdings=..., sections=...)`` gives a recipe's
``main``: Hydra composes ``conf/<config_name>.yaml`` against the recipe's schema (every run's keys and its
own ``sections``, :func:`~torchrl_esrl.run.schema.recipe_schema`); the config, the task, the memory and
disk the run needs and what the run directory holds are checked once, before Hydra writes into the run directory
(:class:`ValidateBeforeRun`; in a multirun, each job checks its own); then ``train(cfg, run)``
runs with a :class:`Run` that seeds, makes kernels deterministic, logs, evaluates, checkpoints at
every iteration boundary and resumes from the run directory's last readable checkpoint. A
finished run is not run again: one line says where its results are, exit 0. A config error, a
numerical fault, or a checkpoint or run file that cannot be written ends the run with one line on
stderr, exit 2. What follows the last iteration (the final evaluation, the figure, ``summary.json``)
starts from the last iteration's checkpoint: a rerun of the same command that finds training
complete goes straight to it, and a figure that fails costs only itself (one warning line).
A run directory has one writer (:mod:`~torchrl_esrl.run.lock`): a second run that would write it
is refused the same way, before Hydra writes anything.

SIGTERM and SIGINT stop a run cleanly (:class:`StopOnSignal`): it finishes the step in progress
(a TD3 batch with its updates, an ES generation, a CEM-RL gradient step or generation, an
iteration's end), writes a checkpoint where one can be written (in a TD3 phase, in CEM-RL, at an
iteration boundary: :meth:`Run.stop_point`), says so in its log and on
stderr with the command that resumes it, and exits 128 + the signal's number. Without a step
boundary within :data:`STOP_GRACE_S` seconds, or on a second signal, it stops at once, from its
last checkpoint. Under submitit, the preemption signal (SIGUSR2) stops the run the same way,
then lets submitit requeue the job (docs/runs.md).

The run's own record, ``<run dir>/<recipe>.log``, is the logger ``torchrl_esrl.run`` (Hydra's job
logging, ``conf/hydra/job_logging/run_log.yaml``): when the run started or resumed, every finished
iteration's line, the final returns and what stopped it (a numerical fault or a checkpoint error;
a full disk only on stderr; a stop by a signal), each with its time.
"""
from __future__ import annotations

import errno
import functools
import logging
import os
import shlex
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, read_write
from tqdm.auto import tqdm

from torchrl_esrl.collectors.es_collector import ESCollector
from torchrl_esrl.envs import EnvSizes, EnvSpec, env_sizes
from torchrl_esrl.errors import CheckpointWriteError, ConfigError
from torchrl_esrl.objectives.learner import Learner
from torchrl_esrl.run.algorithm_info import AlgorithmInfo
from torchrl_esrl.run.capacity import Holding, estimate
from torchrl_esrl.run.checkpoint import CHECKPOINT_DIR, RunCheckpoint
from torchrl_esrl.run.console import final_lines, iteration_line, print_config
from torchrl_esrl.run.determinism import make_deterministic
from torchrl_esrl.run.implementation import component, implementation_line, implementations
from torchrl_esrl.run.harness import RunHarness
from torchrl_esrl.run.lock import RunLock
from torchrl_esrl.run.metrics import read_metrics
from torchrl_esrl.run.progress import RunProgress
from torchrl_esrl.run.resume import Finished, algorithm_of, fresh_run_dir, holds_run, prepare_run
from torchrl_esrl.run.schema import recipe_schema
from torchrl_esrl.run.stop import STOP_GRACE_S, StopOnSignal, Stopped

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
log = logging.getLogger(__name__)  # under torchrl_esrl.run: the run directory's <recipe>.log only


class Run(RunHarness):
    """The plumbing around a recipe's loop: the harness (seeding, metrics, evaluation, summary),
    determinism, the loop's progress and the checkpoint.

    A recipe builds its components, hands them to :meth:`start`, then loops over
    :meth:`iterations`; what the loop body logs is checkpointed after it.
    """

    def __init__(self, cfg: DictConfig, run_dir: Path, algorithm: AlgorithmInfo | str, holdings: Callable[[DictConfig, EnvSizes], list[Holding]] = lambda cfg, sizes: []):
        self.progress = RunProgress()  # iteration, TD3 frames, the TD3 phase under way, the resumable clock
        super().__init__(cfg, run_dir, algorithm, clock=self.progress.wall_time)
        self.holdings = holdings  # what the recipe builds: the expected checkpoint size
        make_deterministic()
        self.checkpoint: RunCheckpoint | None = None
        self.stop = StopOnSignal()  # installed by recipe_main's main

    def start(self, actor, **components) -> None:
        """Start the run, or continue it: evaluate ``actor`` as built, checkpoint ``components``
        (name -> object with ``state_dict``/``load_state_dict``) from now on, and restore them from
        the run directory's last checkpoint, if it holds one."""
        self.attach_actor(actor)
        self.threads = threads_used(components)
        cfg = self.cfg
        config = OmegaConf.to_container(cfg, resolve=True)
        size = estimate(self.holdings(cfg, env_sizes(EnvSpec.from_config(cfg.env)))).checkpoint  # checked before each save
        self.checkpoint = RunCheckpoint(self.run_dir, config, cfg.checkpoint.every_frames, cfg.checkpoint.keep_last, algorithm=self.algorithm, expected_bytes=size,
                                        every_generations=cfg.checkpoint.every_generations, progress=self.progress, evaluator=self.evaluator, **components)
        restored = self.checkpoint.restore()
        if restored is not None and self.log_.path.exists():
            rows = read_metrics(self.log_.path)  # as of the checkpoint: the summary's frame counts if no iteration is left
            self.last_row = rows[-1] if rows else {}
        what = f"{self.algorithm} on {cfg.env.id}, seed {cfg.seed}, {cfg.iterations} iterations, implementation={cfg.implementation}"
        if restored is None:
            log.info(f"started: {what}")
        else:
            log.info(f"resumed at iteration {self.progress.iteration + 1} from {restored}: {what}")
        self.pieces = implementations(cfg, **components)  # what computes each piece, and why a fast one handed over
        line = implementation_line(self.pieces)
        log.info(line)
        print(line, flush=True)

    def iterations(self, desc: str) -> Iterator[int]:
        """The outer loop from where the run stands; after each iteration's body, a checkpoint and,
        when the output is not a terminal, the iteration's line (:func:`~torchrl_esrl.run.console.iteration_line`)."""
        first, total = self.progress.iteration, int(self.cfg.iterations)
        progress = bool(self.cfg.logger.progress)
        # tqdm's disable=None: a bar on a terminal only; elsewhere one plain line per iteration
        self.bar = tqdm(range(first, total), desc=desc, unit="it", initial=first, total=total, disable=None if progress else True)
        lines = progress and self.bar.disable
        for iteration in self.bar:
            yield iteration
            self.progress.finish_iteration()
            written = self.checkpoint.save()
            line = iteration_line(self.last_row, total, self.initial_return)
            log.info(line)
            if lines:
                print(line, flush=True)
            self.stop.check("at the end of an iteration", lambda: written)

    def on_td3_batch(self, frames: int, *_) -> None:
        """``td3_phase``'s ``on_batch`` hook: a checkpoint every ``checkpoint.every_frames`` TD3 frames,
        and the phase on the progress bar (every 5% of the phase's frames); a stop point (with a checkpoint)."""
        self.checkpoint.maybe_save_mid_phase()
        self.stop.check("in the TD3 phase", self.checkpoint.save_if_new)
        collected, total = self.progress.td3_phase.collected, int(self.cfg.td3.frames_per_iteration)
        if collected % max(1, total // 20) < frames:
            self.show_phase(f"TD3 {collected}/{total} frames")

    def on_es_generation(self, index: int) -> None:
        """``es_phase``'s ``on_generation`` hook: the phase on the progress bar, a checkpoint every
        ``checkpoint.every_generations`` generations, and a stop point (with a checkpoint). Both
        checkpoints are taken where the ES phase runs inline (on the main thread), and hold the
        phase where the recipe hands it to the run (:class:`~torchrl_esrl.algorithm.es_phase.GenerationsDone`
        as ``progress.phase``); a stop in a phase run alongside the TD3 phase resumes from the last one."""
        total = int(self.cfg.es.generations_per_iteration)
        self.show_phase(f"ES {index + 1}/{total} generations")
        inline = threading.current_thread() is threading.main_thread()
        if inline and self.progress.phase is not None:
            self.checkpoint.maybe_save_after_generation(index + 1, total)
        self.stop.check(f"after ES generation {index + 1}/{total}", self.checkpoint.save_if_new if self.progress.phase is not None else None)

    def evaluate(self, vector: torch.Tensor, episodes: int | None = None, seeds=None) -> float:
        """:meth:`RunHarness.evaluate`; an evaluation of the per-iteration stream that the restored
        checkpoint already counts (the run stopped after it, within the iteration) is not played
        again: its recorded return is given, and the evaluator's stream goes on from the checkpoint."""
        if seeds is not None:
            return super().evaluate(vector, episodes, seeds)
        recorded = self.progress.recorded_evaluation()
        if recorded is not None:
            return recorded
        value = super().evaluate(vector, episodes)
        self.progress.record_evaluation(value)
        return value

    def stop_point(self, where: str | Callable[[], str]) -> None:
        """A stop point where the run's state is whole (its components and ``progress.phase``),
        ``where`` in words (or a function giving them, called only on a stop): on a stop request,
        a checkpoint of this point, then the stop."""
        self.stop.check(where, self.checkpoint.save_if_new)

    def position(self) -> str:
        """Where the run stands, in words (the stop line); within a recipe's phase, as the phase says."""
        phase = self.progress.phase
        return f"iteration {self.progress.iteration + 1}/{self.cfg.iterations}, " + (phase.position() if phase is not None else f"TD3 frame {self.progress.frames_now}")


def threads_used(components: dict) -> dict:
    """The threads a run's phases use (``summary.json``'s ``threads``): the TD3 phase's torch
    threads (its learner's) and the ES backend's MuJoCo threads, where the run has them."""
    threads = {}
    learner = component(components, Learner)
    if getattr(learner, "num_threads", None) is not None:
        threads["td3"] = int(learner.num_threads)
    es_threads = getattr(getattr(component(components, ESCollector), "backend", None), "nthread", None)
    if es_threads is not None:
        threads["es"] = int(es_threads)
    return threads


@dataclass(frozen=True)
class Recipe:
    """What a recipe gave :func:`recipe_main` (``main.recipe``): its config and its schema (and
    the name its top config lists first), what it runs and what it holds."""

    config_name: str
    schema: type
    schema_name: str
    algorithm: AlgorithmInfo | Callable[[DictConfig], AlgorithmInfo]
    holdings: Callable[[DictConfig, EnvSizes], list[Holding]]


def recipe_main(
    train: Callable[[DictConfig, Run], dict],
    config_name: str,
    algorithm: AlgorithmInfo | Callable[[DictConfig], AlgorithmInfo],
    holdings: Callable[[DictConfig, EnvSizes], list[Holding]],
    sections: Mapping[str, type] | None = None,
) -> Callable[[], None]:
    """The ``main`` of a recipe whose loop is ``train(cfg, run)``, composed from ``conf/<config_name>.yaml``.
    ``algorithm``: what it runs (a function of the config for a recipe with variants), named in
    ``summary.json``; ``holdings(cfg, sizes)``: what it builds (:mod:`~torchrl_esrl.run.capacity`),
    checked against the machine before any work; ``sections``: the config sections of its own
    (key -> a dataclass of fields with defaults and checks, declared beside the recipe or its
    component), added to every run's keys under ``<config_name>_schema``, the name its top config
    lists first (``run_schema`` without). ``main.recipe`` holds all of it (:class:`Recipe`)."""
    schema, schema_name = recipe_schema(config_name, sections)

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)
    @functools.wraps(train)  # Hydra names the job, and its log file, after the recipe's file
    def main(cfg: DictConfig) -> None:
        checked = _checked(cfg, recipe)
        if checked is None:  # a finished multirun job: said so, nothing to do
            return
        cfg, run_dir, lock = checked
        stop = StopOnSignal().install()
        run = None
        try:
            print_config(cfg)  # only with logger.print_config=true; Hydra saves it in <run dir>/.hydra/
            run = Run(cfg, run_dir, algorithm_of(algorithm, cfg), holdings)
            run.stop = stop
            summary = train(cfg, run)
            signal.setitimer(signal.ITIMER_REAL, 0)  # finished before a stop point: a finished run
        except Stopped as stopped:
            _stopped(stopped, run, run_dir, stop)
        except FloatingPointError as fault:
            _stop(f"numerical fault: {fault}; run stopped, last good checkpoint kept in {run_dir / CHECKPOINT_DIR}")
        except CheckpointWriteError as error:
            _stop(f"checkpoint error: {error}")
        except OSError as error:
            full = error.errno in (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
            if not full and not _in_run_dir(error.filename, run_dir):
                raise
            # on stderr only: the log's file may be on the same full disk
            once = "there is room" if full else "it can be written"
            _exit(f"disk error: {error.strerror} writing {error.filename or run_dir}; run stopped, last good checkpoint kept in {run_dir / CHECKPOINT_DIR}; rerun the same command to resume once {once}")
        finally:
            stop.uninstall()
            if lock is not None:
                lock.release()  # a multirun job: its process may run other jobs next
        ending = final_lines(summary, run_dir, info=run.info)  # returns of the returned, TD3 and initial policies; where the files are
        log.info(f"finished: {ending}")
        print(ending)

    recipe = {"algorithm": algorithm, "holdings": holdings}
    _recipe.update(recipe)  # for ValidateBeforeRun
    cli = functools.partial(run_cli, main)
    cli.recipe = Recipe(config_name, schema, schema_name, algorithm, holdings)
    return cli


# ------------------------------------------------------------------ config checks, once a launch
_prepared: list[tuple[DictConfig | None, Path]] = []  # what ValidateBeforeRun checked, for the task function
_held: list[RunLock] = []  # the locks ValidateBeforeRun took: held until the process ends
_recipe: dict = {}  # prepare_run's arguments of the recipe whose main runs (recipe_main)


class ValidateBeforeRun(Callback):
    """Hydra callback: every check before Hydra creates or writes the run directory. A finished
    run exits 0 here, with one line, before Hydra writes anything; ``fresh=true`` moves the run
    (and Hydra's files) to a new directory next to one that holds a run."""

    def on_run_start(self, config, **kwargs: Any) -> None:
        run_dir = Path(str(config.hydra.run.dir)).expanduser()
        if config.get("fresh") and not config.resume:
            run_dir = fresh_run_dir(run_dir)
            if run_dir != Path(str(config.hydra.run.dir)).expanduser():
                print(f"fresh=true: {config.hydra.run.dir} holds a run; this one starts in {run_dir}", file=sys.stderr, flush=True)
                with read_write(config.hydra):
                    config.hydra.run.dir = str(run_dir)  # run_job reads it next
        try:
            cfg, run_dir, lock = _locked(config, run_dir, _recipe)
        except Finished as finished:
            print(finished, flush=True)
            raise SystemExit(0) from None
        except ConfigError as error:
            _exit(f"config error: {error}")  # Hydra turns a callback's exception into a warning: exit here
        _held.append(lock)  # for the life of the process
        _prepared.append((cfg if config.resume else None, run_dir))


def _locked(cfg: DictConfig, run_dir, recipe: dict) -> tuple[DictConfig, Path, RunLock]:
    """:func:`prepare_run`, then the run directory's lock; checked again under the lock if the
    directory holds a run (another writer may have changed it between the two)."""
    checked, run_dir = prepare_run(cfg, run_dir, **recipe)
    field = "resume" if cfg.resume else "hydra.run.dir"
    lock = RunLock(run_dir).acquire(field)
    try:
        if holds_run(run_dir):
            checked, run_dir = prepare_run(cfg, run_dir, **recipe)
    except BaseException:
        lock.release()
        raise
    return checked, run_dir, lock


def _checked(cfg: DictConfig, recipe: dict) -> tuple[DictConfig, Path, RunLock | None] | None:
    """The config to run (the saved one on ``resume``), the run directory and, for a multirun
    job, the lock it holds until the job ends; None for a finished multirun job (its line printed)."""
    if _prepared:  # a single run, checked (and locked) by ValidateBeforeRun
        saved, run_dir = _prepared.pop()
        return (cfg if saved is None else saved), run_dir, None
    run_dir = HydraConfig.get().runtime.output_dir  # a multirun job: Hydra has written its files there
    if cfg.get("fresh") and not cfg.resume:
        run_dir = fresh_run_dir(run_dir)
    try:
        return _locked(cfg, run_dir, recipe)
    except Finished as finished:
        print(finished, flush=True)
        return None
    except ConfigError as error:
        _exit(f"config error: {error}")


def _stopped(stopped: Stopped, run: Run | None, run_dir: Path, stop: StopOnSignal) -> None:
    """The end of a run stopped by a signal: where it stopped, the checkpoint it resumes from and
    the command that resumes it, in its log and on stderr; exit 128 + the signal's number."""
    signal.setitimer(signal.ITIMER_REAL, 0)
    for signum in StopOnSignal.SIGNALS:  # the line is written whole; the handlers are restored on the way out
        signal.signal(signum, signal.SIG_IGN)
    name = signal.Signals(stopped.signum).name
    started = run is not None and run.checkpoint is not None
    where = f"at {run.position()}" if started else "while starting"
    if stopped.at_once:
        where += f" (no step boundary within {STOP_GRACE_S} s, or a second signal)"
    elif stopped.where:
        where += f" ({stopped.where})"
    latest = run.checkpoint.latest() if started else None
    if stopped.written is not None:
        saved = f"checkpoint {stopped.written.name} written"
    elif latest is not None:
        saved = f"no checkpoint here, it resumes from {latest.name}"
    else:
        saved = "no checkpoint yet, it starts again"
    message = f"stopped by {name} {where}; {saved}; to resume: {resume_command(run_dir)}"
    log.warning(message)
    print(message, file=sys.stderr, flush=True)
    stop.hand_over()  # submitit: requeue the job (exits)
    raise SystemExit(128 + stopped.signum)


def resume_command(run_dir: Path) -> str:
    """The command line that continues the run in ``run_dir``: the one that started it, with the
    run (or sweep) directory spelled out where it came from the config (a timestamp) and
    without ``fresh=true`` (which would start another)."""
    argv = list(getattr(sys, "orig_argv", [sys.executable, *sys.argv]))
    multirun = any(a in ("-m", "--multirun") for a in argv)
    try:
        hydra_cfg = HydraConfig.get()
    except ValueError:
        hydra_cfg = None
    if multirun:
        key, value = "hydra.sweep.dir", (hydra_cfg.sweep.dir if hydra_cfg is not None else None)
    else:
        key, value = "hydra.run.dir", run_dir
    if any(a.startswith("fresh=") for a in argv) and not multirun:
        argv = [a for a in argv if not a.startswith("fresh=") and not a.startswith(f"{key}=")]
    if value is not None and not any(a.startswith(f"{key}=") for a in argv):
        argv.append(f"{key}={Path(str(value)).absolute()}")
    return shlex.join(argv)


def _in_run_dir(filename, run_dir: Path) -> bool:
    """Whether ``filename`` (an OSError's) is a file of the run directory (its summary, figure, metrics)."""
    return filename is not None and Path(os.fsdecode(filename)).absolute().is_relative_to(Path(run_dir).absolute())


def _exit(message: str) -> None:
    print(message, file=sys.stderr)
    raise SystemExit(2)


def _stop(message: str) -> None:
    """A started run's end on an error: in its log, then as :func:`_exit`."""
    log.error(message)
    _exit(message)


def one_line(error: BaseException) -> str:
    """A configuration error as one line: the field, the value and what is allowed."""
    from omegaconf.errors import OmegaConfBaseException

    cause = error
    while cause.__cause__ is not None and not isinstance(cause, OmegaConfBaseException):
        cause = cause.__cause__
    message = str(cause).strip().splitlines()[0] if str(cause).strip() else type(cause).__name__
    full_key = getattr(cause, "full_key", None)
    if isinstance(cause, OmegaConfBaseException) and full_key and not message.startswith(str(full_key)):
        message = f"{full_key}: {message}"
    if cause is not error and str(error).strip():
        message = f"{message} ({str(error).strip().splitlines()[0]})"
    options = getattr(error, "options", None)  # hydra's MissingConfigException: a config group choice
    if options:
        message = f"{message} (allowed: {', '.join(sorted(options))})"
    return message


def run_cli(main) -> None:
    """Call a ``@hydra.main`` function; config errors exit 2 with one line on stderr."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    full_error = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"  # let Hydra raise instead of printing a multi-line report
    try:
        main()
    except (ConfigError, HydraException, OmegaConfBaseException) as error:
        if full_error == "1":
            raise
        _exit(f"config error: {one_line(error)}")
    finally:  # leave the environment as it was (a caller's later Hydra errors print normally)
        if full_error is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = full_error
