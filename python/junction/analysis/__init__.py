from .stats import T975, mean_ci, t_interval, t_quantile
from .runs import SMOOTHING, first_reach, read_progress, smoothed_scene_success, without_rolled_back
