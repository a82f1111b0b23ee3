"""Writes results/REPORT.md from the analyses of recipes/analyze.py.

python recipes/report.py
python recipes/report.py analyses='{short: results/short, thesis: results/thesis}'
"""

from __future__ import annotations

import logging
import subprocess
from pathlib import Path

import hydra
from omegaconf import DictConfig

import torchrl_mbmf
from torchrl_mbmf.analysis.report import write_report
from torchrl_mbmf.checks import check_input_file, check_output_path, check_recipe_overrides

log = logging.getLogger("report")


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            check=True,
        )
        return out.stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


@hydra.main(config_path="../configs", config_name="report", version_base="1.3")
def main(cfg: DictConfig) -> None:
    check_recipe_overrides(cfg)  # a +key=... typo is refused, not ignored
    # Every input and the output are checked before any work.
    analyses = {Path(p).name: p for p in cfg.analyses}
    missing = [p for p in cfg.analyses if not (Path(p) / "analysis.json").exists()]
    if missing:
        raise FileNotFoundError(
            f"no analysis.json for {missing}; run recipes/analyze.py for them first"
        )
    notes = None if cfg.notes is None else check_input_file(cfg.notes, "notes")
    appendices = [check_input_file(a, "appendices") for a in cfg.appendices or ()]
    out = check_output_path(cfg.out, "out", folder=False)
    write_report(
        analyses,
        out,
        notes=notes,
        commands=list(cfg.commands),
        appendices=appendices,
        version=torchrl_mbmf.__version__,
        commit=_commit(),
    )
    log.info("wrote %s", out)


if __name__ == "__main__":
    main()
