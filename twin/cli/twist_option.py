"""``--twist RATE``: the option of ``twin live`` and ``twin replay`` that states the catheter's unmeasured twist.

A fibre without a twist measurement cannot see its catheter twist about its own axis; where the setup twists it
(friction in a sheath, a torqued hub) the reconstruction errs by a rotation of its curvature that grows along the
fibre, and the confidence tube (:mod:`twin.uncertainty`) carries that only when told how much: the model error's
twist term (:attr:`twin.uncertainty.ModelError.twist`), the 1σ of a twist rate constant along the fibre, rad/m.
The twin's default model error has none (0 under connect constraints; about 0.08 rad/m in grooves and tubes,
:data:`twin.uncertainty.TWIN_SHEATH_TWIST` = 0.82 rad/m in the twin's sheath). ``--twist`` sets it for the tube
the command draws and reports (``tube_twist_rad_per_m`` in ``--json``; docs/figures.md).
"""

from __future__ import annotations

import argparse
import math

__all__ = ["add_twist_argument", "check_twist"]

HELP = ("1σ of the catheter's twist rate that the fibre does not measure, rad/m (default 0; 0.82 is the twin's "
        "sheath): the confidence tube's model error carries it (--json: tube_twist_rad_per_m)")


def add_twist_argument(parser: argparse.ArgumentParser) -> None:
    """Declare ``--twist RATE`` (rad/m, default 0) on a command's parser."""
    parser.add_argument("--twist", type=float, default=0.0, metavar="RATE", help=HELP)


def check_twist(args: argparse.Namespace) -> None:
    """Refuse, in one line (the commands' check of their numbers, before any source opens), a ``--twist`` that is
    not a finite number of rad/m >= 0, or that has no confidence tube to widen (the paper's method)."""
    if not (math.isfinite(args.twist) and args.twist >= 0):  # NaN too
        raise ValueError(f"--twist must be a finite twist rate in rad/m >= 0 (0.82: the twin's sheath), got "
                         f"{args.twist}")
    if args.twist and args.method != "material":
        raise ValueError(f"--twist {args.twist:g}: the confidence tube it widens covers the material method only, "
                         f"not --method {args.method}")
