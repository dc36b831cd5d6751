"""A run's time from its records (torchrl_esrl/report/timing.py): the holds of pauses.txt
subtracted from its attempts' seconds and, where the records place them, from its training clock;
an attempt missing from timing.txt. Records written by hand, each number worked out below."""
import json
from pathlib import Path

import pytest

from torchrl_esrl.report import Algorithms, run_time, write_timing
from torchrl_esrl.report.tables import write_runs_table
from torchrl_esrl.run.algorithm_info import discover

ROOT = Path(__file__).resolve().parents[1]
ALGORITHMS = Algorithms(discover(ROOT / "recipes"), reference="es_td3_buffers", normalise_by="td3", es_alone="es")


def record(folder: Path, clock: float, seed: int = 0, **files: str) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (folder / name.replace("_", ".")).write_text(text)
    summary = {"env": "Walker2d-v5", "algorithm": "td3", "seed": seed, "final_return": 1.0, "wall_time_s": clock}
    (folder / "summary.json").write_text(json.dumps(summary))
    return {"summary": summary, "metrics": [], "dir": folder}


def test_holds_are_taken_off_the_attempts_and_off_the_clock_where_the_records_place_them(tmp_path):
    """Piece 0 (1,000 s, killed) and piece 1 (1,000 s, exit 0); clock 1,900 s, so piece 0 lost at most
    2,000 - 1,900 = 100 s. Held 100 s ending 800 s before piece 0's end (on the clock), 30 s ending
    10 s before it (maybe lost work: not placed), 60 s in piece 1 (on the clock)."""
    pieces = ("piece 0 commit aaa start 2026-01-01T00:00:00Z seconds 1000 peak_rss_mib 900 killed\n"
              "piece 1 commit bbb start 2026-01-01T01:00:00Z seconds 1000 peak_rss_mib 900 load_mean 1.95 load_max 2.40 exit 0\n")
    pauses = ("pause 2026-01-01T00:01:40Z\nresume 2026-01-01T00:03:20Z\npause 2026-01-01T00:16:00Z\nresume 2026-01-01T00:16:30Z\n"
              "pause 2026-01-01T01:05:00Z\nresume 2026-01-01T01:06:00Z\n")
    time = run_time(record(tmp_path / "run", 1900.0, pieces_txt=pieces, pauses_txt=pauses))
    assert (time.seconds, time.held, time.counted) == (2000, 190.0, 160.0)
    assert time.seconds_net == 1810.0 and time.clock_net == (1710.0, 1740.0) and not time.missing
    assert time.per_attempt == [130.0, 60.0] and time.attempts[1].load == (1.95, 2.40) and time.attempts[0].load is None


def test_an_attempt_that_ran_alone_to_the_end_holds_every_hold_and_a_short_record_is_missing_an_attempt(tmp_path):
    alone = run_time(record(tmp_path / "a", 400.0, timing_txt="w td3_seed0: exit 0 after 410 s on commit abc\n",
                            pauses_txt="pause 2026-01-01T00:01:00Z\nresume 2026-01-01T00:02:40Z\npause 2026-01-01T00:05:00Z\n"))
    assert (alone.held, alone.counted, alone.open_holds) == (100.0, 100.0, 1)  # a pause with no resume is counted apart
    assert alone.clock_net == (300.0, 300.0) and alone.seconds_net == 310.0
    short = run_time(record(tmp_path / "b", 2716.2, timing_txt="h cem_rl_buffers_seed1: exit 0 after 1427 s on commit abc\n"))
    assert short.missing and short.seconds_net == pytest.approx(2716.2)  # at least its clock
    started_over = "w td3_seed0: exit 137 after 15 s on commit abc (started over)\nw td3_seed0: exit 0 after 90 s on commit def started 2026-01-01T00:00:20Z\n"
    both = run_time(record(tmp_path / "c", 85.0, timing_txt=started_over))
    assert [a.started_over for a in both.attempts] == [True, False] and both.seconds == 105 and not both.missing


def test_the_runs_log_places_holds_its_attempts_cannot(tmp_path):
    """Two attempts without start times; the log: attempt 1 finished an iteration at 00:10 and was
    killed, attempt 2 finished one at 01:10 and the run at 01:20. A hold before 00:10 and one before
    01:20 were on the clock; one at 00:11, after attempt 1's last iteration, may have been lost."""
    log = ("[2026-01-01 00:00:00,000] started: td3 on Walker2d-v5\n[2026-01-01 00:10:00,000] iteration 1/2 | elapsed 0:10:00\n"
           "[2026-01-01 01:00:00,000] resumed at iteration 2 from checkpoint-1: td3\n[2026-01-01 01:10:00,000] iteration 2/2 | elapsed 0:20:00\n"
           "[2026-01-01 01:20:00,000] finished: td3 on Walker2d-v5\n")
    pauses = ("pause 2026-01-01T00:02:00Z\nresume 2026-01-01T00:03:00Z\npause 2026-01-01T00:11:00Z\nresume 2026-01-01T00:12:00Z\n"
              "pause 2026-01-01T01:12:00Z\nresume 2026-01-01T01:13:00Z\n")
    timing = "w td3_seed0: exit 137 after 900 s on commit abc\nw td3_seed0: exit 0 after 1200 s on commit abc\n"
    time = run_time(record(tmp_path / "run", 1500.0, timing_txt=timing, pauses_txt=pauses, run_log=log))
    assert (time.held, time.counted) == (180.0, 120.0)


def test_timing_and_runs_tables_give_the_net_seconds_with_the_held_beside(tmp_path):
    held = record(tmp_path / "r0", 3335.0, timing_txt="h cem_rl_seed2: exit 0 after 3345 s on commit abc\n",
                  pauses_txt="pause 2026-01-01T00:52:59Z\nresume 2026-01-01T01:11:49Z\n")
    short = record(tmp_path / "r1", 2716.0, seed=1, timing_txt="h cem_rl_seed1: exit 0 after 1427 s on commit abc\n")
    text = write_timing([held, short], tmp_path, ALGORITHMS).read_text()
    assert "| Walker2d-v5 | TD3 | 2 | 2466 | 2215 | 2716 | 4931 | 1130 | 1 | 1 |" in text  # 3,345 - 1,130 and at least 2,716
    assert "an attempt is missing from the record" in text and "every hold within it: 2,205 s net of holds" in text
    assert "| Walker2d-v5 | TD3 | 0 | 1: 0 | 2,215 | 1,130 | - | - | abc |" in text  # each run's own row, no load or processor recorded
    loaded = record(tmp_path / "r2", 500.0, seed=2, timing_txt="w td3_seed2: exit killed after 200 s on commit abc load_mean 2.43 load_max 3.19\n"
                    "w td3_seed2: exit 0 after 300 s on commit def started 2026-01-01T00:00:00Z load_mean 2.11 load_max 3.15\n")
    assert "| Walker2d-v5 | TD3 | 2 | 2: killed, 0 | 500 | 0 | 2.11-2.43 / 3.19 (2 of 2) | - | abc, def |" in write_timing([loaded], tmp_path, ALGORITHMS).read_text()
    write_runs_table([held, short], tmp_path, ALGORITHMS)
    rows = [line for line in (tmp_path / "runs.md").read_text().splitlines() if line.startswith("| Walker2d-v5")]
    assert rows[0].endswith("| 36.8 | 18.8 |") and rows[1].endswith("| 45.3 | - |")  # (3,335 - 1,130) / 60; 2,716 / 60


def test_the_runs_table_gives_the_learner_copies_of_a_run_that_makes_them(tmp_path):
    """A run that copies its learner into its population (ERL) logs cumulative counters; the runs table gives
    their last values, and only where some run logs them."""
    from torchrl_esrl.report.records import find_runs

    erl = find_runs([ROOT / "docs" / "results" / "runs" / "table1" / "walker2d" / "erl_seed0"])
    cem = find_runs([ROOT / "docs" / "results" / "runs" / "table1" / "walker2d" / "cem_seed0"])
    last = erl[0]["metrics"][-1]
    write_runs_table(erl + cem, tmp_path, ALGORITHMS)
    table = (tmp_path / "runs.md").read_text().splitlines()
    assert "learner copied in (as elite)" in table[0] and len(table[0].split("|")) == len(table[1].split("|"))
    erl_row = next(line for line in table if "| ERL |" in line)
    assert f"| {int(float(last['injections']))} ({int(float(last['injected_elites']))}) |" in erl_row
    assert "| - | - | - |" in next(line for line in table if "| CEM |" in line)  # TD3 actor, overwrites, copies
    write_runs_table(cem, tmp_path, ALGORITHMS)
    assert "copied" not in (tmp_path / "runs.md").read_text()


def test_each_attempt_names_the_processor_it_ran_on_where_its_line_records_one(tmp_path):
    """Lines as scripts/multibuffer_experiments.sh and scripts/paper_run.sh write them since they
    record scripts/processor.sh's text; beside them an older line (no cpu, a note after it) and a
    started-over line."""
    timing = ("w td3_seed3: exit killed after 200 s on commit abc started 2026-01-01T00:00:00Z load_mean 2.43 load_max 3.19 (reconstructed from the log)\n"
              "w td3_seed3: exit killed after 100 s on commit abc started 2026-01-01T01:00:00Z load_mean 2.00 load_max 2.10 "
              "cpu family 6 model 143 Intel(R) Xeon(R) Platinum 8481C (started over)\n"
              "w td3_seed3: exit 0 after 300 s on commit def started 2026-01-01T02:00:00Z load_mean 2.11 load_max 3.15 cpu family 25 model 17 AMD EPYC\n")
    run = record(tmp_path / "t", 550.0, seed=3, timing_txt=timing)
    time = run_time(run)
    assert [a.cpu for a in time.attempts] == ["", "family 6 model 143 Intel(R) Xeon(R) Platinum 8481C", "family 25 model 17 AMD EPYC"]
    assert [a.started_over for a in time.attempts] == [False, True, False] and time.attempts[2].load == (2.11, 3.15)
    assert ("| 3: killed, killed (started over), 0 | 600 | 0 | 2.00-2.43 / 3.19 (3 of 3) | family 6 model 143 Intel(R) Xeon(R) Platinum 8481C; "
            "family 25 model 17 AMD EPYC; not recorded for 1 of 3 | abc, def |") in write_timing([run], tmp_path, ALGORITHMS).read_text()
    pieces = ("piece 0 commit aaa start 2026-01-01T00:00:00Z seconds 1000 peak_rss_mib 900 load_mean 1.95 load_max 2.40 killed\n"
              "piece 1 commit bbb start 2026-01-01T01:00:00Z cpu family 25 model 17 AMD EPYC seconds 900 peak_rss_mib 950 load_mean 1.90 load_max 2.20 exit 0\n")
    paper = record(tmp_path / "p", 1800.0, pieces_txt=pieces)
    assert [(a.cpu, a.seconds, a.peak_rss_mib, a.ending) for a in run_time(paper).attempts] == [("", 1000, 900, "killed"), ("family 25 model 17 AMD EPYC", 900, 950, "exit 0")]
    text = write_timing([paper], tmp_path, ALGORITHMS).read_text()
    assert "| 0 | aaa | 2026-01-01T00:00:00Z | 1000 | 0 | 900 | 1.95 / 2.40 | - | killed |" in text
    assert "| 1 | bbb | 2026-01-01T01:00:00Z | 900 | 0 | 950 | 1.90 / 2.20 | family 25 model 17 AMD EPYC | exit 0 |" in text
