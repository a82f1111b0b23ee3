from torchrl_mbmf.collectors.lean import CollectorTimes, LeanCollector

__all__ = ["CollectorTimes", "LeanCollector"]
