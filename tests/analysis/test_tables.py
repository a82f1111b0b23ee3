"""torchrl_mbmf.analysis.tables: the IQM cell and the compute split of the result scripts."""

from __future__ import annotations

import json

import pytest

from torchrl_mbmf.analysis.runs import Run
from torchrl_mbmf.analysis.stats import bootstrap_ci, iqm
from torchrl_mbmf.analysis.tables import TIME_PARTS, compute_split, iqm_cell, process_rows


def test_iqm_cell_text_and_record_agree_with_the_statistics():
    values = [3_000.0, 4_200.5, 3_900.0, 5_100.0]
    text, record = iqm_cell(values)
    ci = bootstrap_ci(values)
    assert record["iqm"] == pytest.approx(float(iqm(values)))
    assert record["ci95"] == pytest.approx([ci.low, ci.high])
    assert text == f"{float(iqm(values)):,.0f} [{ci.low:,.0f}, {ci.high:,.0f}] (4)"
    assert iqm_cell([]) == ("n/a", {"values": []})


def _run(folder, summary, resumes=(), rates=()):
    folder.mkdir(parents=True)
    if resumes:
        events = [{"event": "resume", "real_steps": s} for s in resumes]
        (folder / "resume_log.json").write_text(json.dumps(events))
    if rates:
        (folder / "logs/scalars/time").mkdir(parents=True)
        rows = "".join(f"{step},{rate}\n" for step, rate in rates)
        (folder / "logs/scalars/time/steps_per_s.csv").write_text(rows)
    return Run(folder, {"method": "sac_mbpo", "seed": 0}, summary)


def test_compute_split_times_the_last_segment_and_the_whole_run(tmp_path):
    # a run resumed at 500: its first process ran 500 steps at 100/s (5 s), its last process
    # 500 steps at 50/s (10 s); the summary's breakdown covers the last process only
    breakdown = {"update_s": 6.0, "refit_s": 3.0, "env_s": 1.0}
    resumed = _run(
        tmp_path / "a",
        {"real_steps": 1_000, "seconds": 10.0, "time_breakdown": breakdown},
        resumes=[500],
        rates=[(400, 100.0), (500, 100.0), (1_000, 50.0)],
    )
    unfinished = tmp_path / "b"
    unfinished.mkdir()
    split = compute_split([resumed, Run(unfinished, {"method": "sac_mbpo", "seed": 1})])
    assert split["runs"] == 1 and split["segment_starts"] == [500]
    assert split["segment_cpus"] == ["?"]  # no machine.json
    assert split["ms_per_real_step"] == pytest.approx([15.0])  # (5 s + 10 s) / 1,000 steps
    per_step = split["segment_ms_per_real_step"]
    assert list(per_step) == list(TIME_PARTS)
    assert per_step["update_s"] == pytest.approx(12.0)  # 6 s over the last 500 steps
    assert per_step["refit_s"] == pytest.approx(6.0) and per_step["rollout_s"] == 0.0
    assert compute_split([]) == {"runs": 0}


def test_compute_split_at_an_earlier_budget_reads_a_continued_runs_earlier_summary(tmp_path):
    # finished at 1,000 (its second process resumed at 500 on an AVX512 machine), then
    # continued to 2,000 by a third process on an AVX2 machine, which is still running; the
    # folder's machine.json is now the third process's, and the resume at 1,000 kept the one it
    # replaced
    first = {"real_steps": 1_000, "seconds": 10.0, "time_breakdown": {"update_s": 5.0}}
    resumes = [
        {"event": "resume", "real_steps": 500},
        {"event": "resume", "real_steps": 1_000, "previous_summary": first,
         "previous_commit": "abc1234", "previous_machine": {"cpu_capability": "AVX512"}},
    ]  # fmt: skip
    folder = tmp_path / "continued"
    (folder / "logs/scalars/time").mkdir(parents=True)
    (folder / "resume_log.json").write_text(json.dumps(resumes))
    (folder / "machine.json").write_text(json.dumps({"cpu_capability": "AVX2"}))
    (folder / "git_commit.txt").write_text("def5678\n")
    rates = "500,100\n1000,50\n1500,25\n"  # the third process: 500 steps in 20 s
    (folder / "logs/scalars/time/steps_per_s.csv").write_text(rates)
    run = Run(folder, {"method": "sac_mbpo", "seed": 0})
    assert run.summary_at(1_000) == first and run.summary_at(2_000) is None
    assert run.finished_at() == [1_000]
    assert [run.segment_start(s) for s in (400, 500, 501, 1_000, 1_500)] == [0, 0, 500, 500, 1000]
    assert run.machine_at(1_000) == {"cpu_capability": "AVX512"}
    assert run.machine_at(400) == {}  # the resume at 500 predates the record
    assert run.machine_at(1_500) == {"cpu_capability": "AVX2"}
    assert (run.commit_at(1_000), run.commit_at(1_500)) == ("abc1234", "def5678")
    assert run.wall_seconds_to(1_000) == pytest.approx(5.0 + 10.0)
    assert run.wall_seconds == pytest.approx(5.0 + 10.0 + 20.0)
    split = compute_split([run], at_step=1_000)
    assert split["runs"] == 1 and split["real_steps"] == 1_000
    assert split["segment_starts"] == [500] and split["segment_cpus"] == ["AVX512"]
    assert split["commits"] == ["abc1234"]
    assert split["ms_per_real_step"] == pytest.approx([15.0])
    assert split["segment_ms_per_real_step"]["update_s"] == pytest.approx(10.0)  # 5 s / 500
    assert compute_split([run]) == {"runs": 0}  # unfinished now
    assert compute_split([run], at_step=2_000) == {"runs": 0}


def test_process_rows_split_each_kept_process_and_its_refit_cost(tmp_path):
    # three processes: from 0 (killed past 1,500), from 1,000 (its newest checkpoint was
    # damaged, so a third resumed from an older one at 500, cutting the rows past 500): the
    # rows kept are 0-500 by the first process and 500-2,000 by the third
    resumes = [
        {"event": "resume", "real_steps": 1_000},
        {"event": "resume", "real_steps": 500, "previous_machine": {"cpu_capability": "AVX2"}},
    ]
    folder = tmp_path / "run"
    (folder / "logs/scalars/time").mkdir(parents=True)
    (folder / "logs/scalars/model").mkdir(parents=True)
    (folder / "resume_log.json").write_text(json.dumps(resumes))
    machine = {"cpu": "Some Xeon", "cpu_capability": "AVX512"}
    (folder / "machine.json").write_text(json.dumps(machine))
    series = {
        "time/steps_per_s": "500,50\n1000,25\n2000,25\n",  # 10 s, then 1,500 steps in 60 s
        "time/update_s": "500,4\n1000,20\n2000,40\n",
        "time/model_fit_s": "500,1\n1000,10\n2000,30\n",
        "time/rollout_s": "500,0.5\n2000,1.5\n",
        "model/epochs": "500,5\n1000,5\n2000,5\n",
        "model/transitions": "500,400\n1000,800\n2000,1600\n",
    }
    for name, rows in series.items():
        (folder / "logs/scalars" / f"{name}.csv").write_text(rows)
    run = Run(folder, {"method": "sac_mbpo", "seed": 0}, {"real_steps": 2_000})
    assert run.segments() == [(0, 500), (500, 2_000)]
    assert run.wall_seconds == pytest.approx(10.0 + 60.0)
    first, last = process_rows(run)
    assert (first["start"], first["end"], first["cpu"]) == (0, 500, "?")  # record not kept
    assert first["ms_per_real_step"] == pytest.approx(20.0)
    assert first["learn_ms"] == pytest.approx(8.0) and first["refit_ms"] == pytest.approx(2.0)
    assert first["rest_ms"] == pytest.approx(8.0 - 2.0 - 1.0)
    assert first["refit_us_per_transition_epoch"] == pytest.approx(1e6 * 1 / (5 * 400))
    assert (last["start"], last["end"], last["cpu"]) == (500, 2_000, "AVX512")
    assert (first["cpu_name"], last["cpu_name"]) == ("?", "Some Xeon")
    assert last["ms_per_real_step"] == pytest.approx(40.0)
    assert last["learn_ms"] == pytest.approx(1e3 * 60 / 1_500)
    per_epoch = [1e6 * 10 / (5 * 800), 1e6 * 30 / (5 * 1_600)]  # the median of its two refits
    assert last["refit_us_per_transition_epoch"] == pytest.approx(sum(per_epoch) / 2)
    assert last["refit_transitions"] == pytest.approx(1_200.0)
