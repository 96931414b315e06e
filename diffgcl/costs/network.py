"""The learned cost of Guided Cost Learning: ``c_φ(x, u, t) = e^ρ (‖A y(x) + b‖² + w_u ‖u‖²)``.

``y`` is a small ReLU network on *normalised* states (Finn et al. 2016a, §5 of the design brief):
the features ``y: [F]`` are mixed by a learned ``A: [F, F]`` and offset ``b: [F]``, so the cost is
always non-negative and its Gauss–Newton Hessian ``l_xx = 2 JᵀAᵀAJ`` (``J = ∂y/∂x``) is PSD.

Input normalisation: a running mean / variance of the states (``InputNormaliser``) lives in the
parameters' pytree next to the network weights but is *not* trained: :func:`update_normaliser`
merges new data into it outside the gradient, and the cost reads it through ``stop_gradient``.
The standard deviation is floored so that a state component that never moves is not blown up.

Identity features (GCL's ``[I; −I]`` initialisation): the first hidden layer starts with its
first ``2 dX`` units equal to ``relu(z)`` and ``relu(−z)`` of the normalised state ``z``; deeper
layers pass these units through unchanged and the feature layer recombines them, so that initially
``y(x) = [z; random features]`` and the cost starts close to a random quadratic in ``z``. Every
other weight starts random. This needs ``hidden[i] ≥ 2 dX`` and ``n_features ≥ dX``. With no
hidden layers (``hidden=()``) ``y`` is affine in ``z`` and the cost a general PSD quadratic in x.

Optional time input: ``t / horizon`` is appended to the network's input (unnormalised), which lets
the cost vary along the horizon.

Temperature: ``e^ρ`` scales the whole cost, the inverse temperature of the maximum-entropy model
``p(τ) ∝ exp(−c(τ))``. Like the normaliser, ``ρ`` (``CostParams.log_temperature``) is data, not a
trained parameter: the GCL objective fits the cost at ``ρ = 0`` (:mod:`diffgcl.costs.gcl`) and
``ρ`` is set from the demonstrations' action precision (:mod:`diffgcl.costs.temperature`), or left
at 0, where the likelihood alone sets the cost's scale.

Optional feature map (``CostNetwork.feature_map``): the network reads ``φ(x)`` instead of the raw
state — task features a domain expert would use (for the USV: range and bearing to the pole,
closing speed, cross-track and heading error; :meth:`diffgcl.envs.usv.UsvEnv.cost_features`). The
normaliser, the identity initialisation and the Gram form then work on ``φ``; the cost stays a
differentiable function of ``x`` (Gauss–Newton and the LQR differentiate through ``φ``). A
quadratic in the raw state cannot say "keep away from the pole"; a quadratic in such features
can.

Weighted form (``CostNetworkConfig.form = "weighted"``): instead of the Gram form, the state cost is
a non-negative weighted sum of squared residuals ``s(x) = e^ρ Σ_k e^{θ̃_k} (ρ_k(x) / rms_k)²``,
where each residual ``ρ_k`` is zero where a domain expert is content (for the USV: cross-track and
heading error, speed error, soft proximity to the pole;
:meth:`diffgcl.envs.usv.UsvEnv.cost_residuals`), ``rms_k`` is its root mean square on the data (from
the normaliser: ``var + mean²``) and the log weights ``θ̃ = θ − mean(θ): [K]`` are what GCL learns
(their ratios only: the overall scale is the temperature's). This is maximum-entropy IRL's linear
cost in features, so matching the demos' feature expectations is what the likelihood asks; and with
every weight positive the cost keeps its valley where every residual is zero (e.g. back on the
course line once the pole is passed) whatever the weights learn.

Neural form (``CostNetworkConfig.form = "neural"``): the Gram form anchored at a goal,
``s(x) = e^ρ ‖A (y(z(x)) − y(z*))‖²``, where ``z*`` is the normalised input of a goal state the
task names (``CostNetwork.goal_state``; for the USV: on the course line at cruise speed, the pole
far astern, :meth:`diffgcl.envs.usv.UsvEnv.cost_goal_state`). The network is as free as the Gram
form's, but the cost is zero wherever the features equal the goal's, whatever GCL learns: the
valley the weighted form gets from its residuals, without choosing the residuals.

Prior residuals (``CostNetworkConfig.prior_residuals``, neural form): the env names a few
residuals that say where the task goes (``CostNetwork.prior_map``; for the USV the course
residuals — cross-track, heading and speed errors, sway, yaw rate —
:meth:`diffgcl.envs.usv.UsvEnv.cost_prior_residuals`), and the state cost is
``e^ρ [Σ_k e^{θ̃_k} (ρ_k(x)/rms_k)² + e^{θ̃_net} ‖A (y − y*)‖²]``, the weighted form's sum with
the network's term as one more weighted residual (``θ̃`` mean zero, so GCL learns the ratios).
The network reads the task features alone; the prior residuals are normalised by their RMS,
not fed to it. The prior keeps the cost growing without bound away from the course, where a
bounded (``shape_only``) network is flat, and leaves what the prior does not say — for the
USV, keeping clear of the pole — to the network.

Learned barrier (``CostNetworkConfig.barrier_margins``, neural form): the network's term is a
keep-clear cost that rises monotonically as the clearance ``c`` falls, whatever GCL learns; the
network learns where and how much it matters:
``r_k = exp(tanh(A_k y(z̃) + b_k)) · s·softplus((m_k − c)/s) / (m_k √K)``, ``k = 1..K``. ``c`` is
the env's clearance feature (``CostNetwork.clearance_features``, the first of them,
unnormalised); ``m_k`` are the margins (fixed, or learned as ``log m_k`` with
``barrier_learn_margins``) and ``s`` the hinge's softness. ``y`` is the feature network on the
normalised features ``z̃`` with every clearance feature zeroed, so the gate
``exp(tanh(·)) ∈ [1/e, e]`` cannot open a hole at the obstacle: it can only make a margin weigh
up to e² more or less per step in some situations (the pole astern, the boat closing fast).
``A: [K, F]`` and ``b`` start at 0, so the barrier starts as a function of the clearance alone.
Each unit reads the depth inside its margin as a fraction of the margin (about 1 at the
obstacle's edge), so a unit's scale does not grow with its margin; the term's overall scale is
its learned weight. Unlike the anchored network, which has to learn that the pole is to be
avoided at all (on the USV it learned holes beside the pole and a side per seed), the barrier
fixes only *that* nearer is costlier.

The network is flax linen; everything outside it (``CostParams``, :class:`CostNetwork`) is plain,
so the cost is a pure function of an explicit parameter pytree that jit/vmap/scan carry around.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from diffgcl.costs.expansion import expand_cost, expand_residual_cost
from diffgcl.tracing import value_and_jacfwd
from diffgcl.types import Array, CostFn, PRNGKey, QuadraticCost


@struct.dataclass
class InputNormaliser:
    """Running statistics of the state: mean: [dX], var: [dX], count: scalar (samples seen)."""

    mean: Array
    var: Array
    count: Array


@struct.dataclass
class CostParams:
    """Parameters of the network cost.

    net: flax parameter dict (``features`` MLP, ``A: [F, F]``, ``b: [F]``, ``log_w_u: []``) — the
    part that the GCL update trains; norm: :class:`InputNormaliser` — updated from data only;
    log_temperature: scalar ``ρ``, the cost is scaled by ``e^ρ`` — set from data only.
    """

    net: dict
    norm: InputNormaliser
    log_temperature: Array


#: The shape-only neural form's maps of the features (``CostNetworkConfig.squash``).
SQUASHES = {"tanh": jnp.tanh, "asinh": jnp.arcsinh}


@dataclass(frozen=True)
class CostNetworkConfig:
    """Shape and initialisation of the cost network.

    hidden: widths of the ReLU layers of ``y`` (the paper: 2 layers of 24–52 units);
    n_features: F, the size of ``y`` (the paper: 20–100); identity_init: GCL's ``[I; −I]`` first
    layer; linear_skip: the first dX features are a linear map of ``z`` (initialised to ``z``)
    next to the MLP's ``n_features − dX`` (replaces the identity path; with weight decay on the
    MLP the cost stays quadratic unless the data ask for more); action_weight: initial ``w_u``;
    learn_action_weight: train ``log w_u`` with the rest; time_input: append ``t / horizon`` to
    the input; std_floor: lower bound of the normaliser's standard deviation (in the state's own
    units); a_scale: standard deviation of the initial
    entries of ``A`` times ``sqrt(F)``; features: ``"state"`` — the network reads the raw
    state — or ``"env"`` — it reads the env's ``cost_features(x)`` (task features), or with the
    weighted form its ``cost_residuals(x)``; form: ``"gram"`` (``‖A y + b‖²``, the paper's),
    ``"neural"`` (``‖A (y − y*)‖²``, the Gram form anchored at the network's ``goal_state``) or
    ``"weighted"`` (learned non-negative weights on squared residuals; module docstring; hidden,
    n_features, identity_init, linear_skip, time_input and a_scale are unused); shape_only (the
    ``"neural"`` form): the network learns the cost's shape and not its scale, as the weighted
    form learns only its weights' ratios — ``‖Â (tanh y − tanh y*)‖²`` with ``Â = A`` rescaled
    to the Frobenius norm ``a_scale·√F`` it starts near, so each step's cost is bounded and
    the temperature alone sets the scale; squash: the shape-only features' map, ``"tanh"``
    (bounded: far from the data the cost is flat) or ``"asinh"`` (``asinh y``: it keeps growing
    far from the data, like ``log² |y|``, so that a controller that wanders off still finds the
    way back downhill); prior_residuals (the ``"neural"`` form): beside the network, the env's
    prior residuals (``CostNetwork.prior_map``) with learned weights as in the weighted form, the
    network's term one more weighted residual (module docstring); limit_weight: a factor on the
    fixed actuator-limit term ``‖r_lim(u)‖²`` (``CostNetwork.action_limits``), for costs whose
    learned part is far larger per step than the weighted form's (about 1 per residual on the
    demos) and would outweigh the limits; mirror (the ``"neural"`` form): the network's term is
    averaged over the task's mirror image, ``½(‖r(φ)‖² + ‖r(Mφ)‖²)`` with ``M`` the env's sign
    flips of the features under reflection (``CostNetwork.feature_mirror``; for the USV the
    reflection across the course line), so the learned cost cannot prefer one side, as the
    weighted form's squared residuals cannot. Unmirrored, each USV network seed passes the pole
    on one side whatever the situation; mirrored, the runs still kept to one side and passed
    closer (docs/usv_cost_form.md), so the USV presets leave it off; barrier_margins (the
    ``"neural"`` form): when not empty, the network's term is a learned keep-clear barrier
    instead of the anchored Gram form (module docstring; shape_only, squash and a_scale are then
    unused, and so is the goal state), one unit per margin, starting at these
    clearances (in the clearance feature's units, m for the USV); barrier_softness: the width
    over which each unit's hinge is rounded (same units); barrier_learn_margins: GCL moves the
    margins too (off: they stay where they start, and GCL learns the gate and the term's
    weight). Learned, the USV's margins ran off to both ends (0.4 m and 175–280 m) and the runs
    passed at 0.1× the demos' clearance (docs/usv_cost_form.md).
    """

    hidden: tuple[int, ...] = (32, 32)
    n_features: int = 32
    identity_init: bool = True
    action_weight: float = 1e-2
    learn_action_weight: bool = True
    linear_skip: bool = False
    time_input: bool = False
    horizon: int = 1
    std_floor: float = 1e-2
    a_scale: float = 1.0
    features: str = "state"
    form: str = "gram"
    shape_only: bool = False
    squash: str = "tanh"
    prior_residuals: bool = False
    limit_weight: float = 1.0
    mirror: bool = False
    barrier_margins: tuple[float, ...] = ()
    barrier_softness: float = 1.0
    barrier_learn_margins: bool = False

    def __post_init__(self):
        if self.form not in ("gram", "neural", "weighted"):
            raise ValueError(
                f"CostNetworkConfig: form {self.form!r}; 'gram' (‖A y + b‖²), 'neural' "
                "(‖A (y − y*)‖², zero at a goal) or 'weighted' (learned weights on squared "
                "residuals)"
            )
        for name in ("shape_only", "prior_residuals", "mirror", "barrier_margins"):
            if getattr(self, name) and self.form != "neural":
                raise ValueError(
                    f"CostNetworkConfig: {name} is for form 'neural', not {self.form!r}"
                )
        if self.time_input and self.horizon < 2:
            raise ValueError(
                f"CostNetworkConfig: time_input needs horizon, the demos' window in steps "
                f"(got {self.horizon})"
            )
        if self.squash not in SQUASHES:
            raise ValueError(
                f"CostNetworkConfig: squash {self.squash!r}; choose one of {sorted(SQUASHES)}"
            )
        if not isinstance(self.barrier_margins, tuple):
            raise ValueError(
                "CostNetworkConfig: barrier_margins is a tuple of margins in metres, () for no "
                f"learned barrier; got {self.barrier_margins!r}"
            )
        if any(not m > 0.0 for m in self.barrier_margins) or not self.barrier_softness > 0.0:
            raise ValueError(
                "CostNetworkConfig: barrier_margins and barrier_softness must be > 0, got "
                f"{self.barrier_margins} and {self.barrier_softness}"
            )
        if not self.limit_weight > 0.0:
            raise ValueError(
                f"CostNetworkConfig: limit_weight must be > 0, got {self.limit_weight}"
            )
        if self.features not in ("state", "env"):
            raise ValueError(
                f"CostNetworkConfig: features {self.features!r}; 'state' (the raw state) or "
                "'env' (the env's cost_features)"
            )


def _identity_kernel(rows: int, cols: int, dX: int, mode: str, base_init):
    """A kernel init that writes an identity block for the first ``dX`` state units.

    mode ``"split"``: columns [0, dX) = I and [dX, 2dX) = −I on input rows [0, dX) (first layer);
    ``"pass"``: the block [0, 2dX) × [0, 2dX) is the identity (hidden layers);
    ``"merge"``: columns [0, dX) = rows [0, dX) minus rows [dX, 2dX) (feature layer);
    ``"direct"``: columns [0, dX) = I on input rows [0, dX) (feature layer without hidden layers).
    Columns of the identity block receive nothing from other rows, so the path is exact.
    """

    def init(key, shape, dtype=jnp.float32):
        kernel = base_init(key, shape, dtype)
        eye = jnp.eye(dX, dtype=dtype)
        if mode == "split":
            kernel = kernel.at[:, : 2 * dX].set(0.0)
            kernel = kernel.at[:dX, :dX].set(eye).at[:dX, dX : 2 * dX].set(-eye)
        elif mode == "direct":
            kernel = kernel.at[:, :dX].set(0.0).at[:dX, :dX].set(eye)
        elif mode == "pass":
            kernel = kernel.at[:, : 2 * dX].set(0.0)
            kernel = kernel.at[: 2 * dX, : 2 * dX].set(jnp.eye(2 * dX, dtype=dtype))
        else:
            kernel = kernel.at[:, :dX].set(0.0)
            kernel = kernel.at[:dX, :dX].set(eye).at[dX : 2 * dX, :dX].set(-eye)
        return kernel

    del rows, cols
    return init


class FeatureNetwork(nn.Module):
    """``y(z)``: ReLU MLP from the network input ``z: [dIn]`` to features ``[n_features]``.

    ``identity_dim`` > 0 switches on the identity path for the first ``identity_dim`` inputs.
    ``linear_dim`` > 0: the first ``linear_dim`` features come from a separate linear layer named
    ``linear`` (initialised to pass the first ``linear_dim`` inputs through), the other
    ``n_features − linear_dim`` from the MLP.
    """

    hidden: Sequence[int]
    n_features: int
    identity_dim: int = 0
    linear_dim: int = 0
    param_dtype: jnp.dtype = jnp.float32

    @nn.compact
    def __call__(self, z: Array) -> Array:
        base = nn.initializers.lecun_normal()
        if self.linear_dim:
            lin_init = _identity_kernel(0, 0, self.linear_dim, "direct", base)
            y_lin = nn.Dense(
                self.linear_dim, kernel_init=lin_init, param_dtype=self.param_dtype, name="linear"
            )(z)
            mlp = FeatureNetwork(
                self.hidden,
                self.n_features - self.linear_dim,
                identity_dim=0,
                param_dtype=self.param_dtype,
                name="mlp",
            )
            return jnp.concatenate([y_lin, mlp(z)])
        h = z
        d = self.identity_dim
        for i, width in enumerate(self.hidden):
            init = base
            if d:
                init = _identity_kernel(h.shape[-1], width, d, "split" if i == 0 else "pass", base)
            h = nn.relu(nn.Dense(width, kernel_init=init, param_dtype=self.param_dtype)(h))
        mode = "merge" if self.hidden else "direct"
        init = _identity_kernel(h.shape[-1], self.n_features, d, mode, base) if d else base
        return nn.Dense(self.n_features, kernel_init=init, param_dtype=self.param_dtype)(h)


def untempered(params: CostParams) -> CostParams:
    """The same cost at ``ρ = 0`` (what the GCL objective fits)."""
    return params.replace(log_temperature=jnp.zeros_like(params.log_temperature))


def init_normaliser(dX: int, dtype=jnp.float32) -> InputNormaliser:
    """Zero mean, unit variance, no samples seen."""
    return InputNormaliser(
        mean=jnp.zeros(dX, dtype), var=jnp.ones(dX, dtype), count=jnp.zeros((), dtype)
    )


def update_normaliser(
    norm: InputNormaliser, X: Array, mask: Array | None = None
) -> InputNormaliser:
    """Merge states ``X: [..., dX]`` (optionally ``mask: [...]``, 1 = use) into the running moments.

    Parallel (Chan et al.) merge of the stored moments with the batch's, so the result equals the
    moments of all data seen. The first batch replaces the initial unit variance.
    """
    X = X.reshape(-1, X.shape[-1])
    w = jnp.ones(X.shape[0], X.dtype) if mask is None else mask.reshape(-1).astype(X.dtype)
    n_b = w.sum()
    mean_b = (w[:, None] * X).sum(0) / jnp.maximum(n_b, 1.0)
    var_b = (w[:, None] * (X - mean_b) ** 2).sum(0) / jnp.maximum(n_b, 1.0)
    n = norm.count + n_b
    delta = mean_b - norm.mean
    mean = norm.mean + delta * n_b / jnp.maximum(n, 1.0)
    m2 = norm.var * norm.count + var_b * n_b + delta**2 * norm.count * n_b / jnp.maximum(n, 1.0)
    var = jnp.where(n > 0, m2 / jnp.maximum(n, 1.0), norm.var)
    return InputNormaliser(mean=mean, var=var, count=n)


@dataclass(frozen=True)
class CostNetwork:
    """The cost ``c_φ`` for states of size ``dX`` and actions of size ``dU``; all methods are pure
    functions of an explicit :class:`CostParams` and written for one ``(x, u, t)``.
    ``param_dtype``: dtype of new parameters (float64 in the tests); ``feature_map``: an optional
    feature map ``φ(x: [dX]) -> [dF]`` the network reads instead of ``x`` (module docstring);
    ``action_limits``: optional fixed residuals of the action ``r_lim(u): [K]`` (the env's
    actuator limits, e.g. :meth:`diffgcl.envs.usv.UsvEnv.action_limit_residuals`), known and not
    learned: the cost gains ``‖r_lim(u)‖²``. Where the env clips its commands, the linearised
    dynamics lose all authority beyond the limits, and without this term the LQR pushes the
    actions there for nothing (on the USV the controllers blew up within five iterations and
    the boat circled with its nozzle hard over). ``goal_state``: the state ``x*`` (dX floats)
    where the ``"neural"`` form's cost is zero (required by that form, unused by the others).
    ``prior_map``: the env's prior residuals ``ρ(x): [K]`` that the ``"neural"`` form with
    ``prior_residuals`` weighs beside its network (e.g.
    :meth:`diffgcl.envs.usv.UsvEnv.cost_prior_residuals`); required by that option.
    ``feature_mirror``: ±1 per entry of the feature map's output (of ``x`` without one), the
    sign each takes when the task is reflected
    (e.g. :attr:`diffgcl.envs.usv.UsvEnv.cost_feature_mirror`); required by ``mirror``.
    ``clearance_features``: indices into the feature map's output of the features that are
    functions of the clearance to the obstacle, the first being the clearance itself (e.g.
    :attr:`diffgcl.envs.usv.UsvEnv.cost_clearance_features`); required by ``barrier_margins``."""

    config: CostNetworkConfig
    dX: int
    dU: int
    param_dtype: object = jnp.float32
    feature_map: Callable[[Array], Array] | None = None
    action_limits: Callable[[Array], Array] | None = None
    goal_state: tuple[float, ...] | None = None
    prior_map: Callable[[Array], Array] | None = None
    feature_mirror: tuple[float, ...] | None = None
    clearance_features: tuple[int, ...] | None = None

    def __post_init__(self):
        if self.config.form == "neural" and self.goal_state is None:
            raise ValueError("CostNetwork: form 'neural' needs a goal_state (the env's)")
        if self.config.mirror != (self.feature_mirror is not None):
            raise ValueError(
                "CostNetwork: network.mirror needs a feature_mirror (the env's "
                "cost_feature_mirror), and a feature_mirror needs network.mirror"
            )
        if self.feature_mirror is not None:
            d = self.network_input_dim
            if len(self.feature_mirror) != d or any(
                v not in (1.0, -1.0) for v in self.feature_mirror
            ):
                raise ValueError(
                    f"CostNetwork: feature_mirror must be {d} signs (±1), one per network input; "
                    f"got {self.feature_mirror}"
                )
        if bool(self.config.barrier_margins) != (self.clearance_features is not None):
            raise ValueError(
                "CostNetwork: network.barrier_margins needs clearance_features (the env's "
                "cost_clearance_features), and clearance_features need network.barrier_margins"
            )
        if self.clearance_features is not None:
            d = self.network_input_dim
            idx = self.clearance_features
            if not idx or any(not 0 <= i < d for i in idx) or len(set(idx)) != len(idx):
                raise ValueError(
                    f"CostNetwork: clearance_features must be distinct indices in [0, {d}) of "
                    f"the network's input, the clearance first; got {idx}"
                )
        if self.config.prior_residuals != (self.prior_map is not None):
            raise ValueError(
                "CostNetwork: network.prior_residuals needs a prior_map (the env's "
                "cost_prior_residuals), and a prior_map needs network.prior_residuals"
            )

    def _out_dim(self, fn: Callable[[Array], Array]) -> int:
        shape = jax.eval_shape(fn, jax.ShapeDtypeStruct((self.dX,), self.param_dtype))
        return int(shape.shape[0])

    @property
    def network_input_dim(self) -> int:
        """Size of the state part of the network's input: ``dF`` with a feature map, else
        ``dX``."""
        return self.dX if self.feature_map is None else self._out_dim(self.feature_map)

    @property
    def prior_dim(self) -> int:
        """K, the number of prior residuals (0 without ``prior_residuals``)."""
        return 0 if self.prior_map is None else self._out_dim(self.prior_map)

    @property
    def state_input_dim(self) -> int:
        """Size of what the normaliser sees: the network's state input and the prior residuals
        after it."""
        return self.network_input_dim + self.prior_dim

    def state_input(self, x: Array) -> Array:
        """``φ(x)`` with a feature map, else ``x``, followed by the prior residuals ``ρ(x)`` with
        ``prior_residuals``: [state_input_dim]."""
        f = x if self.feature_map is None else self.feature_map(x)
        return f if self.prior_map is None else jnp.concatenate([f, self.prior_map(x)])

    def fit_normaliser(self, X: Array, mask: Array | None = None) -> InputNormaliser:
        """The normaliser's statistics from states ``X: [..., dX]`` (of :meth:`state_input`)."""
        flat = X.reshape(-1, X.shape[-1])
        inputs = jax.vmap(self.state_input)(flat)
        norm = init_normaliser(self.state_input_dim, inputs.dtype)
        return update_normaliser(norm, inputs, None if mask is None else mask.reshape(-1))

    @property
    def _features(self) -> FeatureNetwork:
        d = self.network_input_dim
        return FeatureNetwork(
            hidden=self.config.hidden,
            n_features=self.config.n_features,
            identity_dim=d if self.config.identity_init else 0,
            linear_dim=d if self.config.linear_skip else 0,
            param_dtype=self.param_dtype,
        )

    def _input_dim(self) -> int:
        return self.network_input_dim + (1 if self.config.time_input else 0)

    def init(self, key: PRNGKey) -> CostParams:
        """Random parameters (identity path if configured), unit normaliser."""
        cfg = self.config
        d = self.state_input_dim
        if cfg.form == "weighted":
            net = {
                "log_w": jnp.zeros(d, self.param_dtype),
                "log_w_u": jnp.log(jnp.asarray(cfg.action_weight, self.param_dtype)),
            }
            return CostParams(
                net=net,
                norm=init_normaliser(d, self.param_dtype),
                log_temperature=jnp.zeros((), self.param_dtype),
            )
        d = self.network_input_dim
        if cfg.linear_skip and cfg.n_features <= d:
            raise ValueError(f"linear_skip needs n_features > the state input's size {d}")
        too_narrow = min(cfg.hidden, default=2 * d) < 2 * d or cfg.n_features < d
        if cfg.identity_init and not cfg.linear_skip and too_narrow:
            raise ValueError(
                f"identity_init needs hidden widths >= 2 × {d} and n_features >= {d} (the state "
                f"input's size); got hidden={cfg.hidden}, n_features={cfg.n_features}"
            )
        key_mlp, key_a = jax.random.split(key)
        F = cfg.n_features
        mlp = self._features.init(key_mlp, jnp.zeros(self._input_dim(), self.param_dtype))["params"]
        net = {
            "features": mlp,
            "A": cfg.a_scale / jnp.sqrt(F) * jax.random.normal(key_a, (F, F), self.param_dtype),
            "b": jnp.zeros(F, self.param_dtype),
            "log_w_u": jnp.log(jnp.asarray(cfg.action_weight, self.param_dtype)),
        }
        if cfg.barrier_margins:  # the gate starts at 1: a barrier in the clearance alone
            K = len(cfg.barrier_margins)
            net["A"] = jnp.zeros((K, F), self.param_dtype)
            net["b"] = jnp.zeros(K, self.param_dtype)
            net["log_margin"] = jnp.log(jnp.asarray(cfg.barrier_margins, self.param_dtype))
        if cfg.prior_residuals:  # the prior residuals' log weights, then the network's
            net["log_w"] = jnp.zeros(self.prior_dim + 1, self.param_dtype)
        return CostParams(
            net=net,
            norm=init_normaliser(self.state_input_dim, self.param_dtype),
            log_temperature=jnp.zeros((), self.param_dtype),
        )

    def normalise(self, params: CostParams, x: Array) -> Array:
        """``(φ(x) − mean) / max(std, floor)`` (``φ(x) = x`` without a feature map) with the
        statistics held constant: [network_input_dim]."""
        return self._normalise_input(params, self.state_input(x))

    def _normalise_input(self, params: CostParams, f: Array) -> Array:
        """The network's part of ``f`` (the prior residuals left out), normalised."""
        d = self.network_input_dim
        norm = jax.lax.stop_gradient(params.norm)
        std = jnp.maximum(jnp.sqrt(norm.var[:d]), self.config.std_floor)
        return (f[:d] - norm.mean[:d]) / std

    def network_input(self, params: CostParams, x: Array, t: Array | int = 0) -> Array:
        """The feature network's input: the normalised state, with ``t / horizon`` appended when
        ``time_input`` is on: [dIn]."""
        return self._network_input_of(params, self.state_input(x), t)

    def _network_input_of(self, params: CostParams, f: Array, t: Array | int = 0) -> Array:
        z = self._normalise_input(params, f)
        if self.config.time_input:
            tau = jnp.asarray(t, z.dtype) / self.config.horizon
            z = jnp.concatenate([z, tau[None]])
        return z

    def features(self, params: CostParams, x: Array, t: Array | int = 0) -> Array:
        """``y(x, t)``: [F]."""
        return self._apply_features(params, self.network_input(params, x, t))

    def _apply_features(self, params: CostParams, z: Array) -> Array:
        return self._features.apply({"params": params.net["features"]}, z)

    @property
    def is_affine(self) -> bool:
        """Whether ``y`` is affine in the network input (no hidden layers; Gram form)."""
        return self.config.form == "gram" and not self.config.hidden

    def affine_residual_map(self, params: CostParams) -> tuple[Array, Array]:
        """``(M: [F, dIn], m: [F])`` with ``A y(z) + b = M z + m`` for an affine ``y``.

        The Jacobian of the affine feature map at 0 is its weight matrix and its value there the
        offset, so ``M = A ∂y/∂z`` and ``m = A y(0) + b`` hold exactly whatever the layer layout
        (with or without ``linear_skip``). One ``[F, dIn]`` matrix replaces the ``[F, dIn]`` and
        ``[F, F]`` products per state — for F = 32 and dIn = 4 about 9× less arithmetic on the
        cost update's hot path.
        """
        if not self.is_affine:
            raise ValueError(f"the feature network has hidden layers {self.config.hidden}")
        z0 = jnp.zeros(self._input_dim(), params.net["A"].dtype)
        y0, J = value_and_jacfwd(lambda z: self._apply_features(params, z))(z0)
        A = params.net["A"]
        return A @ J, A @ y0 + params.net["b"]

    def temperature(self, params: CostParams) -> Array:
        """``e^ρ`` (scalar), held constant under differentiation (it is set from data)."""
        return jnp.exp(jax.lax.stop_gradient(params.log_temperature))

    def action_weight(self, params: CostParams) -> Array:
        """``w_u`` (scalar); a constant when ``learn_action_weight`` is off."""
        log_w = params.net["log_w_u"]
        if not self.config.learn_action_weight:
            log_w = jax.lax.stop_gradient(log_w)
        return jnp.exp(log_w)

    def state_residual(self, params: CostParams, x: Array, t: Array | int = 0) -> Array:
        """``A y(x, t) + b``: [F] (as ``M z + m`` when ``y`` is affine; under ``vmap`` over
        states ``M`` is formed once, since it does not depend on the state)."""
        return self.residual_of_input(params, self.state_input(x), t)

    def residual_of_input(self, params: CostParams, f: Array, t: Array | int = 0) -> Array:
        """:meth:`state_residual` as a function of the network's input before normalisation,
        ``f = φ(x)`` (``x`` without a feature map)."""
        if self.config.form == "weighted":
            return jnp.exp(0.5 * self.log_weights(params)) * f / self.residual_scale(params)
        if self.config.form == "neural":
            d = self.network_input_dim
            goal = self.state_input(jnp.asarray(self.goal_state, f.dtype))
            r = self._network_residual(params, f, goal, t)
            if self.feature_mirror is not None:
                sign = jnp.asarray(self.feature_mirror, f.dtype)
                f_m = f.at[:d].multiply(sign)
                goal_m = goal.at[:d].multiply(sign)
                r_m = self._network_residual(params, f_m, goal_m, t)
                r = jnp.concatenate([r, r_m]) / jnp.sqrt(jnp.asarray(2.0, f.dtype))
            if not self.config.prior_residuals:
                return r
            w = jnp.exp(0.5 * self.log_weights(params))
            prior = w[:-1] * f[d:] / self.residual_scale(params)[d:]
            return jnp.concatenate([prior, w[-1] * r])
        z = self._network_input_of(params, f, t)
        if self.is_affine:
            M, m = self.affine_residual_map(params)
            return M @ z + m
        return params.net["A"] @ self._apply_features(params, z) + params.net["b"]

    def _network_residual(
        self, params: CostParams, f: Array, goal: Array, t: Array | int = 0
    ) -> Array:
        """The neural form's ``A (y(f) − y(goal))`` (squashed, ``Â``, with ``shape_only``): [F],
        or with ``barrier_margins`` the learned barrier at ``f`` (:meth:`_barrier_residual`);
        ``f``, ``goal``: inputs before normalisation."""
        if self.config.barrier_margins:
            return self._barrier_residual(params, f, t)
        y_goal = self._apply_features(params, self._network_input_of(params, goal, t))
        y, A = self._apply_features(params, self._network_input_of(params, f, t)), params.net["A"]
        if self.config.shape_only:
            squash = SQUASHES[self.config.squash]
            y, y_goal = squash(y), squash(y_goal)
            A = A * (self.config.a_scale * jnp.sqrt(A.shape[0]) / jnp.linalg.norm(A))
        return A @ (y - y_goal)

    def _barrier_residual(self, params: CostParams, f: Array, t: Array | int = 0) -> Array:
        """``exp(tanh(A y(z̃) + b)) ⊙ s·softplus((m − c)/s) / (m √K)``: [K] (module docstring);
        ``f`` before normalisation."""
        idx = jnp.asarray(self.clearance_features)
        c = f[idx[0]]
        z = self._network_input_of(params, f, t).at[idx].set(0.0)
        net = params.net
        gate = jnp.exp(jnp.tanh(net["A"] @ self._apply_features(params, z) + net["b"]))
        s = jnp.asarray(self.config.barrier_softness, f.dtype)
        log_margin = net["log_margin"]
        if not self.config.barrier_learn_margins:
            log_margin = jax.lax.stop_gradient(log_margin)
        margin = jnp.exp(log_margin)
        depth = s * jax.nn.softplus((margin - c) / s) / margin
        return gate * depth / jnp.sqrt(jnp.asarray(len(self.config.barrier_margins), f.dtype))

    def barrier_margins(self, params: CostParams) -> Array:
        """The learned barrier's margins ``m_k``: [K] (``barrier_margins`` on)."""
        return jnp.exp(params.net["log_margin"])

    def residual_scale(self, params: CostParams) -> Array:
        """``rms_k = sqrt(var_k + mean_k²)`` of the residuals on the data seen (floored at
        ``std_floor``), held constant: [K] (weighted form)."""
        norm = jax.lax.stop_gradient(params.norm)
        return jnp.maximum(jnp.sqrt(norm.var + norm.mean**2), self.config.std_floor)

    def log_weights(self, params: CostParams) -> Array:
        """The weighted form's ``θ − mean(θ)``: [K]. Only the weights' ratios are learned; their
        geometric mean stays 1, so that each residual weighs about 1 per step on the demos on
        average and the cost's overall scale is the temperature's (``e^ρ``). Left free, the GCL
        update shrank every weight alike (the demos look costlier than the controllers' samples
        in every residual), the fixed action and limit terms took over, and the controllers
        blew up late in the run."""
        theta = params.net["log_w"]
        return theta - jnp.mean(theta)

    def feature_weights(self, params: CostParams) -> Array:
        """The weighted form's per-residual weights ``e^θ̃ / rms²`` (θ̃ = :meth:`log_weights`):
        [K] (cost per squared unit of each residual, at ρ = 0). With ``prior_residuals``: the
        prior residuals' and, last, the network term's ``e^θ̃`` (its residual has no RMS):
        [K + 1]."""
        w = jnp.exp(self.log_weights(params))
        if self.config.prior_residuals:
            scale = self.residual_scale(params)[self.network_input_dim :]
            return w / jnp.concatenate([scale**2, jnp.ones(1, scale.dtype)])
        return w / self.residual_scale(params) ** 2

    def weighted_residual(self, params: CostParams, x: Array) -> Array:
        """``e^{θ̃/2} ⊙ ρ(x) / rms``: [K] (weighted form)."""
        return self.residual_of_input(params, self.state_input(x))

    def affine_state_quadratic(self, params: CostParams) -> tuple[Array, Array, Array]:
        """``(G: [dIn, dIn], g: [dIn], c: [])`` with ``‖M z + m‖² = zᵀGz + 2gᵀz + c`` (``G = MᵀM``,
        ``g = Mᵀm``, ``c = mᵀm``; see :meth:`affine_residual_map`)."""
        M, m = self.affine_residual_map(params)
        return M.T @ M, M.T @ m, m @ m

    def state_cost(self, params: CostParams, x: Array, t: Array | int = 0) -> Array:
        """``s(x, t) = e^ρ ‖A y(x, t) + b‖²``: scalar.

        For an affine ``y`` through the Gram form of :meth:`affine_state_quadratic` — ``dIn²``
        products per state instead of ``F·dIn``, 8× fewer for F = 32 and dIn = 4 (under ``vmap``
        over states ``G, g, c`` are formed once). Its rounding error is relative to the terms,
        not to ``s``: about ``1e-7 · (zᵀGz + c)`` in float32, far below the cost differences
        that the GCL objective weighs.
        """
        return self.state_cost_of_input(params, self.state_input(x), t)

    def state_cost_of_input(self, params: CostParams, f: Array, t: Array | int = 0) -> Array:
        """:meth:`state_cost` as a function of the network's input before normalisation,
        ``f = φ(x)`` (``x`` without a feature map): what GCL's goal regulariser differentiates."""
        if self.is_affine:
            z = self._network_input_of(params, f, t)
            G, g, c = self.affine_state_quadratic(params)
            return self.temperature(params) * (z @ (G @ z) + 2.0 * (g @ z) + c)
        r = self.residual_of_input(params, f, t)
        return self.temperature(params) * (r @ r)

    def residual(self, params: CostParams, x: Array, u: Array, t: Array | int = 0) -> Array:
        """Residual ``r`` with ``c = ‖r‖²``:
        ``e^{ρ/2} [A y(x, t) + b; sqrt(w_u) u; sqrt(λ_lim) r_lim(u)]``.

        For Gauss–Newton expansion: ``l_xx ≈ 2 J_xᵀJ_x``, ``l_uu ≈ 2 e^ρ (w_u I + J_limᵀJ_lim)``
        (``J_lim`` of ``r_lim``; without limits exactly ``2 e^ρ w_u I``), ``l_ux ≈ 2 J_uᵀJ_x``.
        """
        r = jnp.concatenate([self.state_residual(params, x, t), self.action_residual(params, u)])
        return jnp.sqrt(self.temperature(params)) * r

    def action_residual(self, params: CostParams, u: Array) -> Array:
        """``[sqrt(w_u) u; sqrt(λ_lim) r_lim(u)]`` (the second part only with ``action_limits``;
        ``λ_lim``: ``config.limit_weight``), untempered."""
        r = jnp.sqrt(self.action_weight(params)) * u
        if self.action_limits is None:
            return r
        limits = jnp.sqrt(jnp.asarray(self.config.limit_weight, r.dtype)) * self.action_limits(u)
        return jnp.concatenate([r, limits])

    def action_cost(self, params: CostParams, u: Array) -> Array:
        """``w_u ‖u‖² + λ_lim ‖r_lim(u)‖²`` at ρ = 0: scalar."""
        r = self.action_residual(params, u)
        return r @ r

    def cost(self, params: CostParams, x: Array, u: Array, t: Array | int = 0) -> Array:
        """``c_φ(x, u, t) = s(x, t) + e^ρ (w_u ‖u‖² + λ_lim ‖r_lim(u)‖²)``: scalar."""
        action = self.temperature(params) * self.action_cost(params, u)
        return self.state_cost(params, x, t) + action

    def bind(self, params: CostParams) -> CostFn:
        """The cost as a :data:`~diffgcl.types.CostFn` ``c(x, u, t)`` for fixed parameters."""
        return lambda x, u, t: self.cost(params, x, u, t)

    def bind_residual(self, params: CostParams):
        """``r(x, u, t)`` for fixed parameters (``c = ‖r‖²``)."""
        return lambda x, u, t: self.residual(params, x, u, t)

    def expand(
        self, params: CostParams, X: Array, U: Array, *, gauss_newton: bool = True
    ) -> QuadraticCost:
        """Quadratic expansion about ``X: [T+1, dX]``, ``U: [T, dU]`` (T+1 entries, about the
        trajectory; see :mod:`diffgcl.costs.expansion`). Gauss–Newton (PSD ``l_xx = 2JᵀAᵀAJ``) by
        default, the full Hessian with ``gauss_newton=False``."""
        if gauss_newton:
            return expand_residual_cost(self.bind_residual(params), X, U)
        return expand_cost(self.bind(params), X, U)

    def step_costs(self, params: CostParams, X: Array, U: Array) -> Array:
        """Per-step costs of one trajectory ``X: [T+1, dX]``, ``U: [T, dU]`` -> ``[T+1]``.

        Entries 0..T−1 are ``c(x_t, u_t, t)``; entry T is the terminal ``c(x_T, 0, T)``.
        """
        T = U.shape[0]
        U_full = jnp.concatenate([U, jnp.zeros((1, U.shape[1]), U.dtype)])
        return jax.vmap(self.cost, in_axes=(None, 0, 0, 0))(params, X, U_full, jnp.arange(T + 1))

    def trajectory_cost(self, params: CostParams, X: Array, U: Array) -> Array:
        """``c_φ(τ) = Σ_t c(x_t, u_t, t) + c(x_T, 0, T)``: scalar."""
        return self.step_costs(params, X, U).sum()
