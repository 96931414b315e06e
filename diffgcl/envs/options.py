"""Environment options from text: ``--env-set x0=2,1,0,0,target=0.5,-0.5`` on the command line.

The Python equivalent is the factory's keywords, ``make_env("arm", x0=[2, 1, 0, 0],
target=[0.5, -0.5])``; :func:`parse_env_options` turns the command line's text into those
keywords and :func:`make_env_from_options` checks them against the factory's signature, so that a
misspelt or malformed option is a one-line error naming it.

Syntax: ``KEY=VALUE`` items, several in one string separated by commas (a comma followed by
``name=`` starts a new item), or repeated options. A value is a number, a comma-separated list of
numbers (a vector), a Python literal (``[[..], [..]]`` for several start states), or a string.
A number may be written as a multiple of π: ``0.75pi``, ``-pi``.
"""

from __future__ import annotations

import ast
import inspect
import math
import re

from diffgcl.envs import _REGISTRY, ENV_NAMES, make_env
from diffgcl.types import Env

_ITEM_START = re.compile(r",(?=\s*[A-Za-z_]\w*\s*=)")
_PI = re.compile(r"^\s*([+-]?(?:\d+\.?\d*|\.\d+)?(?:[eE][+-]?\d+)?)\s*\*?\s*pi\s*$")


def _number(text: str) -> float | None:
    """``"1.5"`` -> 1.5, ``"0.75pi"`` -> 0.75π, ``"-pi"`` -> −π; None when not a number."""
    m = _PI.match(text)
    if m:
        coef = m.group(1)
        coef = 1.0 if coef in ("", "+") else -1.0 if coef == "-" else float(coef)
        return coef * math.pi
    try:
        return float(text)
    except ValueError:
        return None


def _value(text: str):
    text = text.strip()
    parts = [p.strip() for p in text.split(",")]
    numbers = [_number(p) for p in parts]
    if all(n is not None for n in numbers):
        return numbers[0] if len(numbers) == 1 else numbers
    expanded = re.sub(r"([+-]?(?:\d+\.?\d*|\.\d+)?)\s*\*?\s*pi\b", _pi_literal, text)
    try:
        return ast.literal_eval(expanded)
    except (ValueError, SyntaxError):
        return text


def _pi_literal(m: re.Match) -> str:
    return repr(_number(m.group(0)))


def parse_env_options(items: list[str] | tuple[str, ...] | str | None) -> dict:
    """``["x0=2,1,0,0,target=0.5,-0.5", "horizon=80"]`` -> ``{"x0": [2.0, 1.0, 0.0, 0.0],
    "target": [0.5, -0.5], "horizon": 80.0}`` (integers stay floats here; the factory casts)."""
    if items is None:
        return {}
    if isinstance(items, str):
        items = [items]
    options: dict = {}
    for group in items:
        for item in _ITEM_START.split(group):
            if "=" not in item:
                raise ValueError(f"--env-set: {item!r} is not KEY=VALUE")
            key, text = item.split("=", 1)
            key = key.strip()
            if not key.isidentifier():
                raise ValueError(f"--env-set: {key!r} is not an option name")
            options[key] = _value(text)
    return options


def env_option_names(name: str) -> tuple[str, ...]:
    """The keyword options of a registered env's factory."""
    import importlib

    module, factory = _REGISTRY[name].split(":")
    fn = getattr(importlib.import_module(module), factory)
    return tuple(
        p.name
        for p in inspect.signature(fn).parameters.values()
        if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)
    )


def make_env_from_options(name: str, options: dict | None = None) -> Env:
    """``make_env(name, **options)`` with the option names checked first; an unknown name or a
    value the factory rejects is a ``ValueError`` of one line naming the env and the option."""
    options = dict(options or {})
    if name not in ENV_NAMES:
        raise ValueError(f"unknown env {name!r}; registered: {', '.join(ENV_NAMES)}")
    known = env_option_names(name)
    for key in options:
        if key not in known:
            raise ValueError(f"--env-set: env {name!r} has no option {key!r}; it has {known}")
    if "horizon" in options:
        options["horizon"] = int(options["horizon"])
    try:
        return make_env(name, **options)
    except (TypeError, ValueError) as err:
        raise ValueError(f"env {name!r} with {options}: {err}") from None


# ---- command line ---------------------------------------------------------------------------


def add_env_options(parser, envs: tuple[str, ...] | None = None) -> None:
    """``--env NAME`` and ``--env-set KEY=VALUE[,KEY=VALUE...]`` (repeatable) on a parser;
    ``envs``: the env names the command supports (default: every registered one)."""
    choices = tuple(envs or ENV_NAMES)
    parser.add_argument("--env", choices=choices, default=choices[0], help="environment")
    parser.add_argument(
        "--env-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="env option, e.g. x0=0.5pi,0.25pi,0,0,target=0.3,-0.4 or horizon=80 (repeatable)",
    )


def env_from_args(args, recorded: dict | None = None) -> tuple[Env, dict]:
    """The env of a command (``args.env``, ``args.env_set``), the options given on the command
    line over ``recorded`` ones (a run folder's); returns ``(env, options)``. Bad options end the
    command with a one-line message."""
    name = getattr(args, "env", None) or (recorded or {}).get("name", "arm")
    options = dict((recorded or {}).get("options", {}))
    try:
        options.update(parse_env_options(getattr(args, "env_set", None)))
        return make_env_from_options(name, options), options
    except ValueError as err:
        raise SystemExit(f"diffgcl: {err}") from None
