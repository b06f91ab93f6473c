"""GRBL 1.1h's homing cycle (``$H``) as planner blocks for the firmware simulator.

As in gnea/grbl's ``limits_go_home``: the compiled cycles run one after another (stock 1.1h:
``HOMING_CYCLE_0`` = Z, then ``HOMING_CYCLE_1`` = X and Y together). In each cycle the axes seek
their switch at ``$25`` for up to 1.5 × the largest max travel (``$130``–``$132``) of the cycle,
pull off ``$27``, locate the switch again at ``$24``, pull off again, each step followed by the
``$26`` ms debounce. A switch not found within the search ends in ``ALARM:9``. The simulated
table is rotary: an axis's switch closes each time its angle passes a multiple of 360°.
Afterwards a homed axis stands at ``-$27`` (or ``-$13x + $27`` when ``$23`` homes it towards
negative angles).
"""

from __future__ import annotations

import math

import numpy as np

from drivers.grbl_protocol import HOMING_SEARCH_SCALAR
from sim.grbl_motion import MotionModel

STOCK_CYCLES = ("Z", "XY")


def parse_cycles(text: str) -> tuple[str, ...]:
    """``"Z,XY"`` -> ``("Z", "XY")``; ValueError for an unknown axis."""
    cycles = tuple(c.strip().upper() for c in str(text).split(",") if c.strip())
    if not cycles or any(set(c) - set("XYZ") for c in cycles):
        raise ValueError(f"homing cycles must be axis letters X, Y, Z separated by commas, "
                         f"got {text!r}")
    return cycles


def plan_homing(motion: MotionModel, cycles, switches: str, now: float,
                offset: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Queue the homing blocks. ``offset`` (3,): the table's true angle minus its machine
    position. Returns the (3,) machine position once homed and the new offset, or None if the
    cycle ends in ALARM:9 (the alarm is queued as the failing search's end event)."""
    s = motion.settings
    pos = motion.planned.copy()
    homed = pos.copy()
    debounce = s[26] / 1000.0
    for cycle in cycles:
        axes = ["XYZ".index(a) for a in cycle]
        direction = {i: -1.0 if int(s[23]) >> i & 1 else 1.0 for i in axes}
        search = HOMING_SEARCH_SCALAR * max(s[130 + i] for i in axes)
        rate = math.sqrt(len(axes))
        to_switch = {i: (-(pos[i] + offset[i]) * direction[i]) % 360.0 for i in axes}
        found = all("XYZ"[i] in switches and to_switch[i] <= search for i in axes)
        target = pos.copy()
        for i in axes:
            target[i] += direction[i] * (to_switch[i] if found else search)
        event = None if found else ("alarm", 9)
        motion.plan(target, s[25] * rate, "home", now, event=event, event_at=1.0)
        if not found:
            return None
        switch = target.copy()
        pulled = switch.copy()
        for i in axes:
            pulled[i] -= direction[i] * s[27]
        for target, feed in ((pulled, s[25]), (switch, s[24]), (pulled, s[25])):
            motion.plan(motion.planned, 0.0, "home", now, pause=debounce)
            motion.plan(target, feed * rate, "home", now)
        motion.plan(motion.planned, 0.0, "home", now, pause=debounce)
        pos = pulled
        for i in axes:
            homed[i] = -s[27] if direction[i] > 0 else -s[130 + i] + s[27]
    return homed, pos + offset - homed

