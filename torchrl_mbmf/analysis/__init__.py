from torchrl_mbmf.analysis.experiments import analyze_experiments, collect_runs
from torchrl_mbmf.analysis.gait import (
    GaitMetrics,
    frame_strip,
    gait_metrics,
    plot_gait,
    record_gait,
    render_states,
)
from torchrl_mbmf.analysis.horizon import horizon_predictions, horizon_table
from torchrl_mbmf.analysis.plots import plot_curves, plot_gait_comparison, save_image
from torchrl_mbmf.analysis.refits import refit_errors, run_refit_errors
from torchrl_mbmf.analysis.report import write_report
from torchrl_mbmf.analysis.runs import (
    Curve,
    Run,
    aggregate_curve,
    compare_intervals,
    final_values,
    fixed_threshold_table,
    group_runs,
    interval_of,
    load_runs,
    ppo_maximum_table,
    ratio_interval,
    steps_interval,
)
from torchrl_mbmf.analysis.stats import (
    Interval,
    bootstrap_ci,
    first_step_reaching,
    interpolate_curve,
    interval_summary,
    iqm,
    iqm_ratio_ci,
    rolling_window_stats,
)
from torchrl_mbmf.analysis.tables import TIME_PARTS, compute_split, iqm_cell
from torchrl_mbmf.objectives.open_loop import HorizonError, multistep_mse, open_loop_rollout

__all__ = [
    "TIME_PARTS",
    "Curve",
    "GaitMetrics",
    "HorizonError",
    "Interval",
    "Run",
    "aggregate_curve",
    "analyze_experiments",
    "bootstrap_ci",
    "collect_runs",
    "compare_intervals",
    "compute_split",
    "final_values",
    "first_step_reaching",
    "fixed_threshold_table",
    "frame_strip",
    "gait_metrics",
    "group_runs",
    "horizon_predictions",
    "horizon_table",
    "interpolate_curve",
    "interval_of",
    "interval_summary",
    "iqm",
    "iqm_cell",
    "iqm_ratio_ci",
    "load_runs",
    "multistep_mse",
    "open_loop_rollout",
    "plot_curves",
    "plot_gait",
    "plot_gait_comparison",
    "ppo_maximum_table",
    "ratio_interval",
    "record_gait",
    "refit_errors",
    "render_states",
    "rolling_window_stats",
    "run_refit_errors",
    "save_image",
    "steps_interval",
    "write_report",
]
