"""Odin-like synthetic ROS bags: a simulated operator avoiding a pole, recorded like the real boat.

The seed's 66 demonstrations of manual obstacle avoidance on the USV Odin (two sets on one day:
set 1 with 19 episodes and no LiDAR, set 2 with 47 episodes with LiDAR; green or grey poles, half
each; varied start and swerve point) are not public. This package writes bags with the same
layout from runs of a simulated human operator on the hull model, so that the whole path bag ->
ingestion -> system identification -> GCL is exercised. :func:`synthesize` writes a set
(:class:`SynthConfig` says what); its parts:

* :mod:`~diffgcl.data.synth.config` — what to write: sensors (:class:`SensorModel`), the two
  layouts' topics (:data:`LAYOUT_TOPICS`), the "other boat" options (:func:`other_boat_config`);
* :mod:`~diffgcl.data.synth.operator_model` — the simulated operator (:class:`OperatorProfile`,
  :func:`draw_profiles`, :func:`simulate`) on the generator's true hull (:func:`true_params`);
* :mod:`~diffgcl.data.synth.scenes` — several poles in the water at once and the recorded drive
  between runs (:func:`repositioning_leg`);
* :mod:`~diffgcl.data.synth.recording` — what the sensors publish about a stretch of the
  timeline (:func:`episode_messages`);
* :mod:`~diffgcl.data.synth.dataset` — the bags and the ``manifest.json`` of a set
  (:func:`synthesize`).

**Files**: one bag per episode (``set1/ep000.bag`` ...), the way a boat crew records one run at a
time; each bag has episode markers 2.5 s after its first and 1 s before its last message, so the
bags also work with ``bag_per="set"`` (one bag per set, episodes one after another, 20 s apart).
``manifest.json`` lists the episodes with their true metadata (pole position and radius, swerve
side, times) and the true hull parameters. The output folder follows
:func:`diffgcl.io.write_folder` (kind :data:`SYNTH_FOLDER`).
"""

from diffgcl.data.synth.config import (
    DEFAULT_START_NS,
    LAYOUT_TOPICS,
    NS,
    OTHER_BOAT_FULL_THRUST,
    OTHER_BOAT_SENSORS,
    SensorModel,
    StampGlitch,
    SynthConfig,
    other_boat_config,
)
from diffgcl.data.synth.dataset import (
    MARKER_LEAD_NS,
    SYNTH_FOLDER,
    EpisodeTruth,
    SynthResult,
    synthesize,
)
from diffgcl.data.synth.operator_model import (
    TRUE_FACTORS,
    OperatorProfile,
    draw_profiles,
    hull_dt,
    simulate,
    true_params,
)
from diffgcl.data.synth.recording import Recording, episode_messages, write_messages
from diffgcl.data.synth.scenes import (
    LEG_CLEARANCE,
    LEG_MIN_TANGENT,
    LEG_TANGENTS,
    repositioning_leg,
    separate_poles,
)

__all__ = [
    "DEFAULT_START_NS",
    "EpisodeTruth",
    "LAYOUT_TOPICS",
    "LEG_CLEARANCE",
    "LEG_MIN_TANGENT",
    "LEG_TANGENTS",
    "MARKER_LEAD_NS",
    "NS",
    "OTHER_BOAT_FULL_THRUST",
    "OTHER_BOAT_SENSORS",
    "OperatorProfile",
    "Recording",
    "SYNTH_FOLDER",
    "SensorModel",
    "StampGlitch",
    "SynthConfig",
    "SynthResult",
    "TRUE_FACTORS",
    "draw_profiles",
    "episode_messages",
    "hull_dt",
    "other_boat_config",
    "repositioning_leg",
    "separate_poles",
    "simulate",
    "synthesize",
    "true_params",
    "write_messages",
]
