"""How demonstrations become the USV task (DESIGN §7b).

:func:`task_windows` puts every demo in its task frame (:mod:`diffgcl.data.task_frame`: origin at
the episode's start, +x along its approach course) and crops it to a window of fixed horizon
around its closest approach to the pole; :func:`make_task_env` builds the USV task env
(:class:`diffgcl.envs.usv.UsvEnv`) on a hull with one condition per demo (its start state and
pole) and the learned cost's clearance margins (:func:`margins_for_clearance`);
:func:`usv_demo_set` gives the demos in that env's layout (state with the pole's radius,
normalised actions, the policy's observations built from the *recorded* ranges), and
:func:`demo_batch_pooled` the batch rGCL trains on.

The demonstrators' own controller for GCL's fusion weights is fitted once on all windows pooled
(one human policy, time-aligned by the closest approach), not per condition: with one demo per
condition a per-condition fit would have no residual to give it a covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from diffgcl.algorithms.rgcl import DemoBatch
from diffgcl.data.demos import DemoError, DemoSet
from diffgcl.envs.usv import PROXIMITY_MARGINS, UsvEnv, encode_ranges, make_usv_env
from diffgcl.sim import hull as hull_sim
from diffgcl.usv.scores import trajectory_metrics

DEFAULT_POLE_RADIUS = 0.5  # m, used when neither the episode nor a manifest gives one


@dataclass(frozen=True)
class UsvTaskConfig:
    """How demos become the USV task.

    before / after: steps kept before and after the closest approach (T = before + after);
    sets: the bag sets whose episodes are used (set 1 of the seed has no LiDAR, set 2 has it);
    observation: the policy's observation set (:data:`diffgcl.envs.usv.OBSERVATIONS`);
    range_encoding: how the policy reads the ranges (:func:`diffgcl.envs.usv.encode_ranges`);
    max_conditions: use at most this many demos (None: all); default_pole_radius: m;
    train_extra: steps the controllers and the policy are trained past the window (their
    horizon is ``horizon + train_extra``; GCL compares the demos with the window's steps only,
    see :mod:`diffgcl.algorithms.rgcl`), so that holding the course after the recordings end is
    trained too (trained on the window alone, policies drifted off the line after it, and runs
    diverged on some seeds: docs/decisions.md); proximity_margins: the clearances (m) of the learned
    cost's barrier residuals (:meth:`diffgcl.envs.usv.UsvEnv.cost_residuals`), or None to take
    them from the demos (:func:`margins_for_clearance`: 5, 10, 15, 20 m on the built-in bags).
    Their largest bounds where the learned cost can still push the boat away: with a 30 m
    margin, boats passed at 1.25–1.35× the demos' clearance (17 m on the built-in bags), with
    20 m at about 1.1×; but with 20 m about one training seed in five passed too close and hit
    the pole, unless it was trained again
    (:attr:`diffgcl.usv.pipeline.UsvRunConfig.retrain_warned`; docs/decisions.md);
    tail: up to this many steps recorded past each window given to GCL's monotonic and goal
    regularisers (:func:`task_tails`; 0: none): the windows end mid-return to the course line,
    and the recordings go on until the boat is back near it (2–106 steps on the built-in bags).
    Read only when GCL has one of those regularisers
    (:attr:`diffgcl.costs.gcl.GCLConfig.reads_tails`; the weighted cost has neither).
    """

    before: int = 120
    after: int = 180
    sets: tuple[str, ...] = ("2",)
    observation: str = "full"
    range_encoding: str = "saturated"
    max_conditions: int | None = None
    default_pole_radius: float = DEFAULT_POLE_RADIUS
    train_extra: int = 150
    proximity_margins: tuple[float, ...] | None = None
    tail: int = 0

    @property
    def horizon(self) -> int:
        return self.before + self.after

    @property
    def training_horizon(self) -> int:
        return self.horizon + self.train_extra


def _chosen_in_task_frame(demos: DemoSet, config: UsvTaskConfig) -> DemoSet:
    """The episodes of ``config.sets``, each in its task frame."""
    from diffgcl.data.task_frame import to_task_frame

    sets = {str(e.get("set")) for e in demos.episodes}
    keep = [i for i, e in enumerate(demos.episodes) if str(e.get("set")) in config.sets]
    if not keep:
        raise DemoError(f"demos: no episode of sets {config.sets} (the data have sets {sets})")
    return to_task_frame(demos.subset(np.asarray(keep)))


def task_windows(demos: DemoSet, config: UsvTaskConfig) -> DemoSet:
    """The chosen sets' episodes in the task frame, cropped around the pole pass (module
    docstring); episodes without a full window are left out with a warning."""
    from diffgcl.data.task_frame import pass_windows

    windows = pass_windows(_chosen_in_task_frame(demos, config), config.before, config.after)
    if config.max_conditions is not None:
        windows = windows.subset(slice(0, config.max_conditions))
    return windows


def task_tails(demos: DemoSet, config: UsvTaskConfig) -> np.ndarray | None:
    """The hull states recorded past each of :func:`task_windows`' windows, in the task frame:
    ``[N, config.tail + 1, DX]`` from the window's last state on, padded with the episode's last
    recorded state (:func:`diffgcl.data.task_frame.pass_tails`); None when ``config.tail`` is 0."""
    from diffgcl.data.task_frame import pass_tails

    if config.tail == 0:
        return None
    chosen = _chosen_in_task_frame(demos, config)
    tails = pass_tails(chosen, config.before, config.after, config.tail)
    if config.max_conditions is not None:
        tails = tails[: config.max_conditions]
    return tails


def cruise_speed_of(windows: DemoSet) -> float:
    """The demos' typical speed over ground (median over all valid steps), m/s."""
    speed = np.hypot(windows.X[..., hull_sim.IX_VX], windows.X[..., hull_sim.IX_VY])
    return float(np.median(speed[windows.mask > 0]))


TUNED_CLEARANCE_M = 17.25  # m, the built-in bags' demos' median clearance (set 2: 17.25)


def margins_for_clearance(clearance_m: float, margins=PROXIMITY_MARGINS) -> tuple[float, ...]:
    """Clearance margins (m) for demos that pass at a median minimum clearance ``clearance_m``:
    ``margins``, tuned for the built-in demos' :data:`TUNED_CLEARANCE_M`, scaled by the ratio and
    rounded to 1 m (unrounded where rounding would merge two or make one 0). The built-in bags
    (17.25 m on set 2, 17.4 m on sets 1 + 2) keep 5, 10, 15, 20 m; demos that pass at 30 m get
    9, 17, 26, 35 m."""
    if not clearance_m > 0 or not np.isfinite(clearance_m):
        raise ValueError(
            f"usv: the demos' median clearance is {clearance_m} m; margins need a positive one "
            "(set UsvTaskConfig.proximity_margins / --margins instead)"
        )
    scaled = np.asarray(margins, float) * (clearance_m / TUNED_CLEARANCE_M)
    rounded = np.round(scaled)
    if rounded[0] <= 0 or np.any(np.diff(rounded) <= 0):
        rounded = scaled
    return tuple(float(m) for m in rounded)


def demo_clearance_median(env: UsvEnv, windows: DemoSet, radii: np.ndarray) -> float:
    """The demos' median minimum clearance (m) to their poles, in ``env``'s hull outline."""
    X = window_states(windows.X, radii)
    return float(np.median(trajectory_metrics(env, X)["min_clearance"]))


def task_margins(windows: DemoSet, radii: np.ndarray, params, config: UsvTaskConfig):
    """The learned cost's clearance margins (m) for ``config``: its own, or taken from the
    windows' median clearance (:func:`margins_for_clearance`)."""
    if config.proximity_margins is not None:
        return config.proximity_margins
    x0 = np.concatenate([windows.X[:, 0, : hull_sim.DX], radii[:, None]], axis=1)
    probe = make_usv_env(x0, params=params, horizon=1)
    return margins_for_clearance(demo_clearance_median(probe, windows, radii))


def make_task_env(
    windows: DemoSet,
    radii: np.ndarray,
    params,
    config: UsvTaskConfig,
    *,
    cruise_speed: float | None = None,
    horizon: int | None = None,
) -> UsvEnv:
    """The USV env on hull ``params`` with one condition per window (its first state and pole);
    the cost's clearance margins are the task's, or taken from the windows
    (:func:`margins_for_clearance`)."""
    x0 = np.concatenate([windows.X[:, 0, : hull_sim.DX], radii[:, None]], axis=1)
    speed = cruise_speed_of(windows) if cruise_speed is None else cruise_speed
    return make_usv_env(
        x0,
        params=params,
        cruise_speed=speed,
        horizon=config.horizon if horizon is None else horizon,
        observation=config.observation,
        range_encoding=config.range_encoding,
        proximity_margins=task_margins(windows, radii, params, config),
    )


def usv_observations(env: UsvEnv, X: np.ndarray, O_hull: np.ndarray) -> np.ndarray:
    """The policy's observations [..., dO] in ``env``'s layout from states ``X: [..., 11]`` and
    the *recorded* observations in the hull layout ``O_hull: [..., 53]`` (ranges, sin ψ, cos ψ,
    ν): the ranges are what the bag's sensors read, the rest comes from the state."""
    n_beams = env.layout.num_beams
    ranges = np.asarray(encode_ranges(O_hull[..., :n_beams], env.range_encoding))
    psi = X[..., hull_sim.IX_PSI]
    heading = np.stack([np.sin(psi), np.cos(psi)], axis=-1)
    nu = O_hull[..., n_beams + 2 : n_beams + 5]
    cross = X[..., hull_sim.IX_PY : hull_sim.IX_PY + 1]
    if env.observation == "ranges":
        return np.concatenate([ranges, nu], axis=-1)
    if env.observation == "radar":
        ranges = ranges[..., env.layout.lidar_beams :]
    return np.concatenate([ranges, heading, nu, cross], axis=-1)


def window_states(X: np.ndarray, radii: np.ndarray) -> np.ndarray:
    """Hull states ``X: [N, T', DX]`` (a window's, or :func:`task_tails`') with each pole's
    radius appended: [N, T', 11]."""
    N, T1, _ = X.shape
    return np.concatenate(
        [X[..., : hull_sim.DX], np.broadcast_to(radii[:, None, None], (N, T1, 1))], -1
    )


def usv_demo_set(env: UsvEnv, windows: DemoSet, radii: np.ndarray) -> DemoSet:
    """The windows in ``env``'s layout: states with the pole radius [N, T+1, 11], normalised
    actions [N, T, 2], the policy's observations [N, T+1, dO] from the recorded ranges, and each
    episode its own condition (``condition = i``)."""
    X = window_states(windows.X, radii)
    offset, scale = np.asarray(env.action_offset), np.asarray(env.action_scale)
    U = (windows.U - offset) / scale
    O = usv_observations(env, X, windows.O)
    episodes = tuple(
        {**e, "condition": i, "pole_radius": float(radii[i])}
        for i, e in enumerate(windows.episodes)
    )
    return DemoSet(X=X, U=U, O=O, mask=windows.mask, dt=windows.dt, env="usv", episodes=episodes)


def demo_batch_pooled(
    demos: DemoSet, dtype=None, env: UsvEnv | None = None, tail: np.ndarray | None = None
) -> DemoBatch:
    """A :class:`~diffgcl.algorithms.rgcl.DemoBatch` with one demo per condition [C, 1, ...] and
    the demonstrators' controller fitted on all demos pooled, shared by every condition; given
    the ``env``, its dynamics linearised about each demo (for ``temperature='demos'``); ``tail``:
    each demo's states past the window in the env's layout ``[C, L+1, dX]``, or None."""
    from diffgcl.costs.demo_controller import fit_demo_controller

    dtype = dtype or jnp.zeros(()).dtype
    X = jnp.asarray(demos.X, dtype)
    U = jnp.asarray(demos.U, dtype)
    pooled = jax.jit(fit_demo_controller)(X, U)
    C = X.shape[0]
    controller = jax.tree.map(lambda a: jnp.broadcast_to(a, (C, *a.shape)), pooled)
    dynamics = None
    if env is not None:
        from diffgcl.algorithms.rgcl import demo_dynamics

        dynamics = demo_dynamics(env, X[:, None], U[:, None])
    if tail is not None:
        if tail.shape[0] != C or tail.shape[-1] != X.shape[-1]:
            raise ValueError(f"demo tails {tail.shape} do not match demos X{tuple(X.shape)}")
        tail = jnp.asarray(tail, dtype)[:, None]
    return DemoBatch(
        X=X[:, None], U=U[:, None], controller=controller, dynamics=dynamics, tail=tail
    )
