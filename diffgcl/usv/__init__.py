"""The USV task end to end: obstacle avoidance learned from ROS bags (DESIGN §7b).

The pieces, each a function that the experiment (``experiments/usv_avoidance.py``) and the CLI
(``diffgcl usv``) chain; :func:`run_usv` chains them all:

1. :mod:`diffgcl.usv.bags` — the Odin-like synthetic bags (:func:`builtin_bags`, from
   :mod:`diffgcl.data.synth`), written once into the cache, or your own bags and topic map
   (:func:`load_bag_demos`);
2. ingestion (:func:`diffgcl.data.ingest.ingest_bags`), then hull identification
   (:func:`identify_hull`, :func:`diffgcl.data.sysid.identify`) on the demonstrations;
3. :mod:`diffgcl.usv.task` — every demo in its task frame, cropped to a window of fixed horizon
   around its closest approach to the pole (:func:`task_windows`); the USV task env on the
   identified hull with one condition per demo (:func:`make_task_env`) and the demos in that
   env's layout (:func:`usv_demo_set`);
4. rGCL (:mod:`diffgcl.algorithms.rgcl`, :func:`diffgcl.algorithms.presets.usv`) learns the cost
   on task features and the MDGPS policy on the observations; a training seed whose controllers
   or policy warn on their own training starts is trained again
   (:mod:`diffgcl.usv.retraining`); references: MDGPS with the hand-written cost and behaviour
   cloning (:mod:`diffgcl.algorithms.bc`);
5. :mod:`diffgcl.usv.evaluation` — situations none of the demos had (pole distance, the boat's
   lateral offset and heading, pole radius and speed drawn from the demos' ranges), rolled out
   on the *true* hull with sensor noise; :mod:`diffgcl.usv.scores` — per episode: collision,
   minimum clearance, back on course, side passed, path distance to the nearest demo, and the
   main figures per training seed.

:mod:`diffgcl.usv.pipeline` holds :func:`run_usv`, its configuration (:class:`UsvRunConfig`,
:func:`fast_run_config`) and its result (:class:`UsvRun`). Every name below is importable from
``diffgcl.usv`` directly.
"""

from diffgcl.usv.bags import (
    BUILTIN_SYNTH,
    bag_paths,
    builtin_bags,
    builtin_demos,
    load_bag_demos,
    pole_radii,
)
from diffgcl.usv.evaluation import SituationRanges, heldout_starts, policy_tracks
from diffgcl.usv.pipeline import (
    FAST_RGCL_OVERRIDES,
    METHODS,
    UsvRun,
    UsvRunConfig,
    fast_run_config,
    identify_hull,
    learned_cost_weights,
    run_over_seeds,
    run_usv,
    usv_rgcl,
)
from diffgcl.usv.retraining import (
    ATTEMPT_FIGURES,
    ON_COURSE_WARN,
    POLICY_CLEARANCE_WARN,
    SENSOR_NOISE_FOLD,
    controller_warnings,
    policy_warnings,
    seed_name,
    train_retrying_warned,
    training_key,
    training_warnings,
)
from diffgcl.usv.scores import (
    collision_profile,
    path_distance_to_demos,
    per_seed_figures,
    score_rollouts,
    situations,
    straight_side,
    trajectory_metrics,
)
from diffgcl.usv.task import (
    DEFAULT_POLE_RADIUS,
    TUNED_CLEARANCE_M,
    UsvTaskConfig,
    cruise_speed_of,
    demo_batch_pooled,
    demo_clearance_median,
    make_task_env,
    margins_for_clearance,
    task_margins,
    task_tails,
    task_windows,
    usv_demo_set,
    usv_observations,
    window_states,
)

__all__ = [
    "ATTEMPT_FIGURES",
    "BUILTIN_SYNTH",
    "DEFAULT_POLE_RADIUS",
    "FAST_RGCL_OVERRIDES",
    "METHODS",
    "ON_COURSE_WARN",
    "POLICY_CLEARANCE_WARN",
    "SENSOR_NOISE_FOLD",
    "SituationRanges",
    "TUNED_CLEARANCE_M",
    "UsvRun",
    "UsvRunConfig",
    "UsvTaskConfig",
    "bag_paths",
    "builtin_bags",
    "builtin_demos",
    "controller_warnings",
    "cruise_speed_of",
    "demo_batch_pooled",
    "demo_clearance_median",
    "fast_run_config",
    "usv_rgcl",
    "heldout_starts",
    "identify_hull",
    "learned_cost_weights",
    "load_bag_demos",
    "make_task_env",
    "margins_for_clearance",
    "path_distance_to_demos",
    "per_seed_figures",
    "pole_radii",
    "policy_tracks",
    "policy_warnings",
    "run_over_seeds",
    "run_usv",
    "score_rollouts",
    "situations",
    "collision_profile",
    "seed_name",
    "straight_side",
    "task_margins",
    "task_tails",
    "task_windows",
    "train_retrying_warned",
    "training_key",
    "training_warnings",
    "trajectory_metrics",
    "usv_demo_set",
    "usv_observations",
    "window_states",
]
