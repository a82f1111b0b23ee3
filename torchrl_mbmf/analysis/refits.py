"""The world model at each refit of a training run: tables 8 and 9 on two kinds of held-out data.

A model-based run refits its world model on all real data every ``world_model.refit_every``
policy updates. Two records of each fit's open-loop error exist:

- **on the policy's own episodes**: before each refit the run scores the model it is about to
  replace on the real transitions collected since that model's fit, which no fit has seen
  (``model/heldout_x_mse_h<h>`` and ``model/heldout_reward_mse_h<h>``, logged at the refit's
  step; see :func:`torchrl_mbmf.world_model.snapshots.heldout_open_loop_errors`);
- **on random-policy episodes**: ``recipes/evaluate_fits.py`` scores every kept fit on the same
  fresh random episodes (``world_models/open_loop_errors.json``), the data of the thesis' own
  tables 8 and 9.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from torchrl_mbmf.analysis.horizon import THESIS_HORIZON_MSE
from torchrl_mbmf.analysis.runs import Run
from torchrl_mbmf.analysis.stats import interval_summary
from torchrl_mbmf.runs.layout import FIT_ERRORS, RunFolder

QUANTITIES = ("x_mse", "reward_mse")


def run_refit_errors(run: Run) -> dict[int, dict[str, dict[int, dict[str, float]]]]:
    r"""One run's open-loop errors per fit, keyed by the transitions the fit was trained on.

    Args:
        run: a model-based training run.

    Returns:
        ``{transitions: {"policy" | "random": {h: {"x_mse", "reward_mse"}}}}``; a source is
        absent where it was not recorded (the last fit of a run has no later policy data, and a
        run that ``recipes/evaluate_fits.py`` has not scored has no random-data errors).

    Examples:
        >>> import tempfile, pathlib
        >>> from torchrl_mbmf.analysis.refits import run_refit_errors
        >>> from torchrl_mbmf.analysis.runs import Run
        >>> d = pathlib.Path(tempfile.mkdtemp())
        >>> (d / "logs/scalars/model").mkdir(parents=True)
        >>> _ = (d / "logs/scalars/model/transitions.csv").write_text("100,100\n300,300\n")
        >>> for q, v in (("x", 0.5), ("reward", 2.0)):
        ...     _ = (d / f"logs/scalars/model/heldout_{q}_mse_h5.csv").write_text(f"300,{v}\n")
        >>> run_refit_errors(Run(d, {"method": "ppo_mpc", "seed": 0}))
        {100: {'policy': {5: {'x_mse': 0.5, 'reward_mse': 2.0}}}, 300: {}}
    """
    fit_steps, fit_sizes = run.scalar("model/transitions")
    fits = [int(v) for v in fit_sizes]
    out: dict[int, dict[str, dict[int, dict[str, float]]]] = {t: {} for t in fits}
    # the held-out errors logged at fit i score the model of fit i - 1
    for h in _logged_horizons(run):
        steps, x = run.scalar(f"model/heldout_x_mse_h{h}")
        _, reward = run.scalar(f"model/heldout_reward_mse_h{h}")
        for step, xv, rv in zip(steps, x, reward, strict=True):
            later = [i for i, s in enumerate(fit_steps) if s == step]
            if not later or later[0] == 0:
                raise ValueError(
                    f"{run.path}: held-out errors logged at step {step} match no refit "
                    f"(fits at {fit_steps.tolist()})"
                )
            scored = fits[later[0] - 1]
            out[scored].setdefault("policy", {})[h] = {"x_mse": float(xv), "reward_mse": float(rv)}
    path = RunFolder(run.path).fits / FIT_ERRORS
    if path.exists():
        for row in json.loads(path.read_text())["fits"]:
            random = out.setdefault(int(row["transitions"]), {}).setdefault("random", {})
            for e in row["errors"]:
                random[int(e["horizon"])] = {q: float(e[q]) for q in QUANTITIES}
    return out


def _logged_horizons(run: Run) -> list[int]:
    folder = RunFolder(run.path).scalars / "model"
    names = folder.glob("heldout_x_mse_h*.csv") if folder.is_dir() else []
    return sorted(int(p.stem.removeprefix("heldout_x_mse_h")) for p in names)


def refit_errors(runs: Sequence[Run]) -> dict[str, Any]:
    """Tables 8 and 9 at every refit, aggregated over the seeds of one configuration.

    Args:
        runs: runs of one model-based configuration (its seeds).

    Returns:
        ``{"runs": [names], "rows": [{"transitions", "source", "horizon", "x_mse",
        "reward_mse", "thesis_x_mse", "thesis_reward_mse"}]}``, ``x_mse`` and ``reward_mse``
        being :func:`~torchrl_mbmf.analysis.stats.interval_summary` over the seeds that
        recorded them; rows are ordered by fit, then source (``policy``, ``random``), then
        horizon.

    Examples:
        >>> from torchrl_mbmf.analysis.refits import refit_errors
        >>> refit_errors([])
        {'runs': [], 'rows': []}
    """
    per_run = [run_refit_errors(r) for r in runs]
    cells: dict[tuple[int, str, int], dict[str, list[float]]] = {}
    for errors in per_run:
        for transitions, sources in errors.items():
            for source, by_h in sources.items():
                for h, values in by_h.items():
                    cell = cells.setdefault((transitions, source, h), {q: [] for q in QUANTITIES})
                    for q in QUANTITIES:
                        cell[q].append(values[q])
    rows = []
    for (transitions, source, h), cell in sorted(cells.items()):
        thesis = THESIS_HORIZON_MSE.get(h, (None, None))
        rows.append(
            {
                "transitions": transitions,
                "source": source,
                "horizon": h,
                **{q: interval_summary(cell[q]) for q in QUANTITIES},
                "thesis_x_mse": thesis[0],
                "thesis_reward_mse": thesis[1],
            }
        )
    return {"runs": [r.name for r in runs], "rows": rows}


__all__ = ["refit_errors", "run_refit_errors"]
