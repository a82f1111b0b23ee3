import pytest
import torch

from torchrl_mbmf.device import DeviceError, resolve_device


def test_cpu_and_auto_without_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cpu")


@pytest.mark.parametrize("value", ["cuda", "cuda:0", "cuda:3"])
def test_cuda_without_gpu_names_the_key(monkeypatch, value):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(DeviceError, match=rf"device='{value}' asks for a CUDA GPU.*no GPU"):
        resolve_device(value)


def test_auto_and_index_with_gpus(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == torch.device("cuda:0")
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    with pytest.raises(DeviceError, match="torch sees 2 GPU"):
        resolve_device("cuda:2")


@pytest.mark.parametrize("value", ["gpu", "cuda:x", "tpu"])
def test_unknown_device(value):
    with pytest.raises(DeviceError, match=f"device='{value}'"):
        resolve_device(value)


def test_train_config_refuses_a_missing_gpu(monkeypatch):
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from torchrl_mbmf.trainers import ConfigError, validate_train_config

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    configs = str(Path(__file__).resolve().parents[2] / "configs")
    with initialize_config_dir(configs, version_base="1.3"):
        cfg = compose("train", overrides=["device=cuda"])
    with pytest.raises(ConfigError, match="device='cuda' asks for a CUDA GPU"):
        validate_train_config(cfg)
