"""Process settings of every entry point (``diffgcl.runtime.prepare_process``): LLVM's expensive
passes off unless the user says otherwise, and bit-identical results with them off."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

FLAG_SCRIPT = textwrap.dedent(
    """
    import os, sys
    from diffgcl.runtime import prepare_process, set_fast_compile
    prepare_process(sys.argv[1])
    import jax
    jax.numpy.ones(2).block_until_ready()  # JAX has started: too late for XLA_FLAGS
    assert not set_fast_compile()
    print("XLA_FLAGS=" + os.environ.get("XLA_FLAGS", ""))
    """
)

# A batched hull rollout with a tanh MLP closing the loop, and its Jacobian to the start states:
# the kinds of loops, matmuls and forward-mode derivatives of a training program.
RESULTS_SCRIPT = textwrap.dedent(
    """
    import hashlib, sys
    import numpy as np
    from diffgcl.runtime import prepare_process
    prepare_process(sys.argv[1])
    import jax, jax.numpy as jnp
    from diffgcl.sim import hull

    params = hull.default_params(jnp.float32)
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(3), 3)
    W1 = 0.3 * jax.random.normal(k1, (hull.DX, 16))
    W2 = 0.3 * jax.random.normal(k2, (16, hull.DU))
    x0 = 0.2 * jax.random.normal(k3, (4, hull.DX))

    def rollout(x):
        def step(x, _):
            u = jnp.tanh(jnp.tanh(x @ W1) @ W2)
            x = hull.hull_step(params, x, u)
            return x, x
        return jax.lax.scan(step, x, None, length=20)[1]

    X = jax.jit(jax.vmap(rollout))(x0)
    J = jax.jit(jax.vmap(jax.jacfwd(lambda x: rollout(x)[-1])))(x0)
    digest = hashlib.sha256(np.asarray(X).tobytes() + np.asarray(J).tobytes()).hexdigest()
    assert np.isfinite(np.asarray(J)).all()
    print("DIGEST", digest)
    """
)


def _python(script: str, cache: str, xla_flags: str | None) -> str:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    out = subprocess.run(
        [sys.executable, "-c", script, cache], env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_prepare_process_turns_off_llvm_expensive_passes_unless_the_user_set_them(tmp_path):
    cache = str(tmp_path / "jax")
    out = _python(FLAG_SCRIPT, cache, None)
    assert "XLA_FLAGS=--xla_llvm_disable_expensive_passes=true\n" in out
    out = _python(FLAG_SCRIPT, cache, "--xla_llvm_disable_expensive_passes=false")
    assert "XLA_FLAGS=--xla_llvm_disable_expensive_passes=false\n" in out


def test_results_are_bit_identical_without_llvm_expensive_passes(tmp_path):
    cache = str(tmp_path / "jax")  # a fresh cache: both programs compiled here, each its way
    digests = {
        flag: _python(RESULTS_SCRIPT, cache, f"--xla_llvm_disable_expensive_passes={flag}")
        for flag in ("true", "false")
    }
    assert all("DIGEST" in out for out in digests.values())
    assert digests["true"] == digests["false"]
