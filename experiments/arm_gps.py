"""GPS (trajectory optimisation) on the two-joint arm with its expert cost (DESIGN §2).

GPS's box2d arm setting: 5 samples per iteration, kl_step 0.2, step_mult in [0.01, 10], initial
controller K = 0, k = 0, Σ = 0.1·I, exploration noise smoothed over σ = 2 steps, 10 iterations.
Dynamics by autodiff through MJX; ``--compare`` (default unless ``--fast``) repeats the run with
GPS's regression fit on the same seeds. A seed succeeds when the noise-free rollout of its final
controller ends within 0.1 rad of q* on both joints over the last 10 steps.

    python experiments/arm_gps.py [--seeds 32] [--fast] [--json PATH] [--out DIR]
                                  [--write-demos DIR] [--x64]

The JSON has ``success_rate``, ``seeds``, ``iterations``, ``seconds_per_run_after_compile``
(all seeds run as one vmapped batch; batch time / seeds), ``compile_seconds``, the first-success
iteration of every seed and, under ``regression``, the same for the regression fit.
"""

from __future__ import annotations

import argparse
import sys

from diffgcl.cli.gps import add_gps_arguments, run_arm_gps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_gps_arguments(parser)
    summary = run_arm_gps(parser.parse_args(argv))
    return 0 if summary["success_rate"] > 0 else 1


if __name__ == "__main__":
    sys.exit(main())
