from torchrl_mbmf.analysis.gait import (
    GaitMetrics,
    frame_strip,
    gait_metrics,
    plot_gait,
    record_gait,
    render_states,
)
from torchrl_mbmf.analysis.horizon import (
    HorizonError,
    horizon_predictions,
    horizon_table,
    multistep_mse,
    open_loop_rollout,
)
from torchrl_mbmf.analysis.stats import (
    Interval,
    bootstrap_ci,
    first_step_reaching,
    interpolate_curve,
    iqm,
    rolling_window_stats,
)

__all__ = [
    "GaitMetrics",
    "HorizonError",
    "Interval",
    "bootstrap_ci",
    "first_step_reaching",
    "frame_strip",
    "gait_metrics",
    "horizon_predictions",
    "horizon_table",
    "interpolate_curve",
    "iqm",
    "multistep_mse",
    "open_loop_rollout",
    "plot_gait",
    "record_gait",
    "render_states",
    "rolling_window_stats",
]
