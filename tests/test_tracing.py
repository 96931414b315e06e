"""diffgcl.tracing.batched_like: values unchanged, every leaf batched under vmap, fewer passes of
a vmapped loop's body."""

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from diffgcl.tracing import batched_like


def test_values_unchanged_and_identity_outside_vmap():
    key = jax.random.PRNGKey(3)
    tree = {
        "x": jnp.array([1.5, -2.0, jnp.inf, jnp.nan]),
        "n": jnp.arange(3, dtype=jnp.int32),
        "b": jnp.array([True, False]),
        "k": jax.random.key(0),
        "none": None,
    }
    out = batched_like(tree, key)
    np.testing.assert_array_equal(out["x"], tree["x"])
    assert out["x"].dtype == tree["x"].dtype and out["n"].dtype == jnp.int32
    np.testing.assert_array_equal(out["n"], tree["n"])
    np.testing.assert_array_equal(out["b"], tree["b"])
    assert out["none"] is None and out["k"] is tree["k"]
    new_style = batched_like(jnp.ones(2), jax.random.key(1))  # a typed key works too
    np.testing.assert_array_equal(new_style, jnp.ones(2))


def test_every_leaf_batched_under_vmap():
    shared = jnp.arange(4.0)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    out = jax.vmap(lambda k: batched_like({"a": shared, "c": jnp.zeros(())}, k))(keys)
    assert out["a"].shape == (3, 4) and out["c"].shape == (3,)
    np.testing.assert_array_equal(out["a"], np.broadcast_to(shared, (3, 4)))


def test_a_vmapped_scan_batches_its_body_once():
    """A carry that the body makes batched costs a second batching pass over the body (each
    pass re-traces what is inside, mjx.step included); batched from the start, one. The passes
    are counted by a custom_vmap function in the body, whose rule runs once per pass."""
    passes = {"n": 0}

    @jax.custom_batching.custom_vmap
    def double(x):
        return 2.0 * x

    @double.def_vmap
    def _double_rule(axis_size, in_batched, x):
        passes["n"] += 1
        return 2.0 * x, in_batched[0]

    def run(key, prebatch):
        def body(carry, _):  # a new function per trace: JAX caches batched bodies
            total, x = carry
            return (total + double(x), x), None

        carry = (jnp.zeros(()), jax.random.normal(key))
        if prebatch:
            carry = batched_like(carry, key)
        return lax.scan(body, carry, None, length=5)[0][0]

    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    counted = {}
    for prebatch in (False, True):
        passes["n"] = 0
        jax.make_jaxpr(jax.vmap(lambda k, p=prebatch: run(k, p)))(keys)
        counted[prebatch] = passes["n"]
    assert counted == {False: 2, True: 1}, counted
    out = jax.vmap(lambda k: run(k, True))(keys)
    ref = jax.vmap(lambda k: run(k, False))(keys)
    np.testing.assert_array_equal(out, ref)


def test_value_and_jacfwd_equals_the_value_and_jacfwd_apart_from_one_trace():
    """A pytree-valued function: the same value and Jacobian as ``f(x)`` and ``jax.jacfwd(f)(x)``,
    with ``f``'s own equations in the program once instead of twice."""
    from diffgcl.tracing import value_and_jacfwd

    def f(x):
        return {"a": jnp.sin(x) * x[0], "b": jnp.sum(jnp.exp(x) ** 2)}

    x = jnp.array([0.3, -1.2, 2.0])
    value, jac = value_and_jacfwd(f)(x)
    want_value, want_jac = f(x), jax.jacfwd(f)(x)
    got, want = jax.tree.leaves((value, jac)), jax.tree.leaves((want_value, want_jac))
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12)

    def count(fn):
        return len(jax.make_jaxpr(fn)(x).jaxpr.eqns)

    apart = count(lambda x: (f(x), jax.jacfwd(f)(x)))
    assert count(value_and_jacfwd(f)) < apart
