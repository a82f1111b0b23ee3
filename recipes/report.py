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
    analyses = {Path(p).name: p for p in cfg.analyses}
    missing = [p for p in cfg.analyses if not (Path(p) / "analysis.json").exists()]
    if missing:
        raise FileNotFoundError(
            f"no analysis.json for {missing}; run recipes/analyze.py for them first"
        )
    write_report(
        analyses,
        cfg.out,
        notes=cfg.notes,
        commands=list(cfg.commands),
        version=torchrl_mbmf.__version__,
        commit=_commit(),
    )
    log.info("wrote %s", cfg.out)


if __name__ == "__main__":
    main()
