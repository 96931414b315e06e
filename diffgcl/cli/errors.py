"""Bad input on the command line: one line on stderr naming the problem and exit status 2,
never a traceback."""

from __future__ import annotations

import functools
import sys

EXIT_BAD_INPUT = 2


def bad_input_errors() -> tuple[type[Exception], ...]:
    """The library's errors for bad input: a bag, a topic map, demos, an output folder, a run
    folder, an MJCF model, a preset or ``--set`` edit."""
    from diffgcl.algorithms.presets import ConfigError
    from diffgcl.algorithms.runner import RunFolderError
    from diffgcl.data.bags import BagError
    from diffgcl.data.demos import DemoError
    from diffgcl.data.topics import TopicMapError
    from diffgcl.io import OutputError
    from diffgcl.sim.mjcf import MJCFError

    return BagError, TopicMapError, DemoError, OutputError, RunFolderError, MJCFError, ConfigError


def guarded(command):
    """``command`` with :func:`bad_input_errors` turned into ``error: <message>`` on stderr and
    :data:`EXIT_BAD_INPUT`."""

    @functools.wraps(command)
    def run(*args, **kwargs) -> int:
        try:
            return command(*args, **kwargs)
        except bad_input_errors() as err:
            print(f"error: {err}", file=sys.stderr)
            return EXIT_BAD_INPUT

    return run
