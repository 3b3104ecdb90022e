"""The simulated cell as the commands take it: the reference cell, perturbed, with a real
cell's effects (``simulator.effects``)."""
from __future__ import annotations

import sys

from flyscan.common import UsageError

__all__ = ["sim_cell", "scan_effects"]


def sim_cell(perturb_seed, effects_text):
    """The simulated cell: the reference, perturbed and with a real cell's effects as asked."""
    from simulator.cell import cell_with_effects

    try:
        return cell_with_effects(perturb_seed, effects_text)
    except ValueError as exc:
        raise UsageError(f"--effects: {exc}") from None


def scan_effects(args, calibration) -> str:
    """``--effects``, or else those of the simulated cell the calibration was made in (its
    provenance says, when ``calibrate --sim`` made it), or else none: a calibration learned in
    the realistic cell is scanned in that cell."""
    if args.effects is not None:
        return args.effects
    made_in = (calibration.provenance.get("simulated_cell") if calibration is not None else None)
    if not isinstance(made_in, dict):
        return "none"
    effects = ",".join(made_in.get("effects") or []) or "none"
    if made_in.get("perturb_seed") != args.perturb_seed:
        print(f"flyscan scan: note: the calibration was made in the simulated cell of "
              f"--perturb-seed {made_in.get('perturb_seed')}, this scan's is "
              f"{args.perturb_seed}: it will not fit", file=sys.stderr)
    print(f"flyscan scan: the simulated cell's effects: {effects} (as where the calibration "
          f"was made; --effects to choose)", file=sys.stderr)
    return effects
