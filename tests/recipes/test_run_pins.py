"""Pinned runs: a tiny config of every method ends with recorded weights and episode returns.

The values were recorded from the code before the training-stack redesign (issue 14); the
redesign keeps every run bit-identical. A change that moves one of these numbers needs a
commit that says why.

The recorded floats are those of the recording machine's float kernels. Where the canary of
``tests/float_kernels.py`` says this machine has the same kernels, the weights' hash and every
logged return are compared exactly. Elsewhere the same code gives other last bits, and training
amplifies them: the Pendulum cases' returns stay within a relative 3e-4 of their pins on the
Intel Xeon machines measured (the largest, ``sac`` at step 800: -813.799 against -814.018), so
they are compared within ``PENDULUM_RTOL``, which still separates a behaviour change (the
``sac`` and ``sac_l2`` pins, one loss apart, differ by 47% at that step); the HalfCheetah cases
drift by 3.5-15% there (a chaotic system over 2,400 steps), so they are skipped, saying why.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from float_kernels import OTHER_KERNELS_REASON, recording_kernels
from rl_helpers import TINY_HALF_CHEETAH, TINY_TRAIN

ROOT = Path(__file__).resolve().parents[2]
# One torch thread: the recorded numbers are those of a single-threaded CPU run.
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}
PENDULUM = ["total_steps=900", *TINY_TRAIN]
HALF_CHEETAH = [*TINY_HALF_CHEETAH, "env.num_envs=2", "total_steps=2400"]
# The PPO-policy runs were pinned when a TanhNormal was PPO's default; they keep it explicitly,
# and the *_gaussian cases pin the default since (the thesis' Gaussian, recorded after that
# change, before any later refactor).
TANH = "ppo.distribution=tanh_normal"
# The SAC runs were pinned when smooth_l1 was SAC's Q distance; they keep it explicitly, and the
# *_l2 cases pin the default since (the squared error, recorded at that change).
SMOOTH_L1 = "sac.loss_function=smooth_l1"
# The SAC runs were pinned when torchrl's biased softplus was the actor's scale; they keep it
# explicitly, and the *_clamped cases pin the default since (SB3's clamped log-std).
SOFTPLUS = "sac.scale=biased_softplus"
CASES = {
    "ppo": ["method=ppo", TANH, *PENDULUM],
    "mpc": ["method=mpc", TANH, *PENDULUM],
    "ppo_mpc": ["method=ppo_mpc", TANH, *PENDULUM],
    "sac": ["method=sac", SMOOTH_L1, SOFTPLUS, *PENDULUM],
    "sac_mpc": ["method=sac_mpc", SMOOTH_L1, SOFTPLUS, *PENDULUM],
    "sac_l2": ["method=sac", SOFTPLUS, *PENDULUM],
    "sac_mpc_l2": ["method=sac_mpc", SOFTPLUS, *PENDULUM],
    "sac_clamped": ["method=sac", *PENDULUM],
    "sac_mpc_clamped": ["method=sac_mpc", *PENDULUM],
    "half_cheetah_ppo_mpc": [TANH, *HALF_CHEETAH],
    "ppo_gaussian": ["method=ppo", *PENDULUM],
    "half_cheetah_ppo_mpc_gaussian": HALF_CHEETAH,
}
#: Relative tolerance of the Pendulum cases' returns on other float kernels (see the docstring).
PENDULUM_RTOL = 5e-3
# name: (params_sha256, [(step, episode return as logged)])
PINS: dict[str, tuple[str, list[tuple[int, str]]]] = {
    "ppo": (
        "575590065f08261f182728c3bfb31e618cdc2bb168b2d21db74cfee315255ad2",
        [(384, "-1655.6181640625"), (576, "-1182.970947265625"), (960, "-1538.3548583984375")],
    ),
    # mpc, ppo_mpc and sac_mpc re-pinned when the world model stopped clipping Pendulum's
    # [-2, 2] actions to [-1, 1] (it takes the env's action bounds)
    "mpc": (
        "8ceab634b78c17ff66444b5396921171a8726eeea6c79017861edf460d5340db",
        [(300, "-1637.8001708984375")],
    ),
    "ppo_mpc": (
        "59cc1ef2e346dda431a1f96119ca551e155645f6295047ed79b64264de359892",
        [(300, "-1637.8001708984375")],
    ),
    "sac": (
        "d4d45e381890c899949b8edf6e61935ca93b1b07ff1ed18d43a0f0c9edc5ceae",
        [(400, "-1604.9744873046875"), (600, "-1668.02734375"), (800, "-814.0181884765625")],
    ),
    "sac_mpc": (
        "cb965c507c9a530ad9761c348ef757c89b70df6460f2b408283395067ad0f67d",
        [(300, "-1500.4385986328125"), (600, "-1763.20849609375"), (800, "-835.1893920898438")],
    ),
    # the default Q distance since 2026-12-05 (squared error; frames_per_batch is the case's own)
    "sac_l2": (
        "010ece100b08152516ebaf5437ab7a43ccb95ce04e1e9b97d488203f8632662e",
        [(400, "-1604.9410400390625"), (600, "-1663.5447998046875"), (800, "-1194.3975830078125")],
    ),
    "sac_mpc_l2": (
        "fce6b31ae556b0974d968aca1a608a01450336640091408d3deebedb1fe78211",
        [(300, "-1500.4385986328125"), (600, "-1763.1094970703125"), (800, "-1022.5355834960938")],
    ),
    # the default actor scale since 2026-12-06 (SB3's clamped log-std; recorded at that change)
    "sac_clamped": (
        "d3fec05dd150a86c6d85717a85c2a0572fd4882bbf16a0484250a4f18066afbe",
        [(400, "-1609.0498046875"), (600, "-1672.6190185546875"), (800, "-942.5475463867188")],
    ),
    "sac_mpc_clamped": (
        "6797d686a778eee20256704e06e509bb880c73a14738aebd7da3a9219ec3bbb2",
        [(300, "-1500.4385986328125"), (600, "-1767.919677734375"), (800, "-1024.07470703125")],
    ),
    "half_cheetah_ppo_mpc": (
        "97625109aa0fb5ae78093e7402b232de99bb5ede205c0f4e99f749543d167da1",
        [(2326, "-167.6564178466797"), (2326, "-299.5785217285156")],
    ),
    # recorded from commit 3e70394 (the Gaussian default, before both stack redesigns)
    "ppo_gaussian": (
        "fa6f75812a062cfa34ae2dd79d5d1ce0b06a0413c8c89ba89b43ba5d6f993457",
        [(384, "-1674.7293701171875"), (576, "-1112.2569580078125"), (960, "-1615.9356689453125")],
    ),
    "half_cheetah_ppo_mpc_gaussian": (
        "279e3a17d98bf38ab2ae6979f921884bf4c3998b30269fc0411d00ceaf66cf58",
        [(2326, "-624.1468505859375"), (2326, "-731.799072265625")],
    ),
}


def _episode_returns(run_dir: Path) -> list[tuple[int, str]]:
    path = run_dir / "logs" / "scalars" / "train" / "episode_return.csv"
    rows = [row.split(",") for row in path.read_text().split()]
    return [(int(step), value) for step, value in rows]


def run_pinned(run_dir: Path, name: str) -> tuple[str, list[tuple[int, str]]]:
    """Runs case ``name`` through the training recipe; returns its digest and returns."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "recipes" / "train.py"), *CASES[name], f"run_dir={run_dir}"],
        cwd=run_dir.parent,
        capture_output=True,
        text=True,
        timeout=600,
        env=ENV,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((run_dir / "summary.json").read_text())
    return summary["params_sha256"], _episode_returns(run_dir)


@pytest.mark.parametrize("name", list(CASES))
def test_run_matches_its_pin(tmp_path, name):
    exact = recording_kernels()
    if not exact and name.startswith("half_cheetah"):
        pytest.skip(f"{OTHER_KERNELS_REASON}; HalfCheetah's returns drift by several percent")
    digest, returns = run_pinned(tmp_path / name, name)
    expected_digest, expected_returns = PINS[name]
    if exact:
        assert returns == expected_returns
        assert digest == expected_digest
    else:
        assert_returns_close(returns, expected_returns, rtol=PENDULUM_RTOL)


def assert_returns_close(
    returns: list[tuple[int, str]], expected: list[tuple[int, str]], rtol: float
) -> None:
    """Same episode ends at the same steps, each return within ``rtol`` of its pin."""
    assert [step for step, _ in returns] == [step for step, _ in expected]
    got = [float(value) for _, value in returns]
    want = [float(value) for _, value in expected]
    assert got == pytest.approx(want, rel=rtol), f"{got} != {want} within rel {rtol}"


def test_assert_returns_close_separates_a_behaviour_change():
    """The tolerance passes the measured cross-machine drift and fails the loss change."""
    sac = PINS["sac"][1]
    drifted = [(400, "-1604.9744873046875"), (600, "-1668.02734375"), (800, "-813.7992553710938")]
    assert_returns_close(drifted, sac, rtol=PENDULUM_RTOL)
    with pytest.raises(AssertionError):
        assert_returns_close(PINS["sac_l2"][1], sac, rtol=PENDULUM_RTOL)
    with pytest.raises(AssertionError):
        assert_returns_close(sac[:2], sac, rtol=PENDULUM_RTOL)


if __name__ == "__main__":  # prints the pins of the code as it stands (PYTHONPATH=tests)
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        for case in CASES:
            print(f"{case!r}: {run_pinned(Path(folder) / case, case)!r},", flush=True)
