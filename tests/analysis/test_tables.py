"""torchrl_mbmf.analysis.tables: the IQM cell and the compute split of the result scripts."""

from __future__ import annotations

import json

import pytest

from torchrl_mbmf.analysis.runs import Run
from torchrl_mbmf.analysis.stats import bootstrap_ci, iqm
from torchrl_mbmf.analysis.tables import TIME_PARTS, compute_split, iqm_cell


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
