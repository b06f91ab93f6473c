"""GRBL 1.1h's planner and steppers for the firmware simulator, as a function of the clock.

Each planner block runs from rest to rest on a trapezoidal profile (no junction blending), so
the position is exact at any instant without a thread (`MotionModel.position`). The model owns
the machine state (``Idle Run Jog Home Hold Alarm``): blocks run only outside ``Hold`` and
``Alarm``. ``instant=True`` completes every block the moment it starts.
"""

from __future__ import annotations

import collections
import dataclasses
import heapq
import itertools
import math

import numpy as np

RUNS_BLOCKS = ("Idle", "Run", "Jog", "Home")
_STATE_OF_KIND = {"run": "Run", "jog": "Jog", "home": "Home"}


@dataclasses.dataclass(frozen=True)
class Profile:
    """Distance (units) along a straight move over time (s): from speed ``v0`` accelerate at
    ``accel`` to ``v_peak``, cruise ``t_cruise`` s, decelerate to rest."""

    v0: float
    v_peak: float
    accel: float
    t_cruise: float

    @classmethod
    def trapezoid(cls, distance: float, speed: float, accel: float) -> Profile:
        v = min(speed, math.sqrt(distance * accel))
        return cls(0.0, v, accel, max((distance - v * v / accel) / v, 0.0) if v > 0 else 0.0)

    @classmethod
    def stop(cls, v0: float, accel: float) -> Profile:
        return cls(v0, v0, accel, 0.0)

    @classmethod
    def pause(cls, seconds: float) -> Profile:
        """Standing still for ``seconds`` (homing's switch debounce)."""
        return cls(0.0, 0.0, 1.0, seconds)

    @property
    def duration(self) -> float:
        return (2 * self.v_peak - self.v0) / self.accel + self.t_cruise

    def at(self, t: float) -> tuple[float, float]:
        """(distance, speed) ``t`` s after the start."""
        a, v0, vp = self.accel, self.v0, self.v_peak
        t_acc = (vp - v0) / a
        if t <= 0:
            return 0.0, v0
        if t < t_acc:
            return v0 * t + 0.5 * a * t * t, v0 + a * t
        s, t = (v0 + vp) / 2 * t_acc + vp * min(t - t_acc, self.t_cruise), t - t_acc - self.t_cruise
        if t <= 0:
            return s, vp
        t = min(t, vp / a)
        return s + vp * t - 0.5 * a * t * t, vp - a * t


@dataclasses.dataclass
class PlannedBlock:
    target: np.ndarray  # (3,) machine units
    rate: float  # requested units/min, limited per axis when the block starts
    kind: str  # "run", "jog" or "home"
    planned_at: float
    event: tuple | None = None  # (kind, argument) fired part-way: ("unplug", None), ("alarm", 9)
    event_at: float = 0.5  # fraction of the block's duration at which ``event`` fires
    pause: float = 0.0  # s standing still instead of moving (a homing debounce)


@dataclasses.dataclass
class Segment:
    origin: np.ndarray
    unit: np.ndarray
    profile: Profile
    t0: float
    kind: str  # block kind, "hold" (decelerating into a hold) or "cancel" (jog cancel)
    end: np.ndarray

    @property
    def end_time(self) -> float:
        return self.t0 + self.profile.duration

    def at(self, now: float) -> tuple[np.ndarray, float]:
        if now >= self.end_time:
            return self.end.copy(), 0.0
        s, v = self.profile.at(now - self.t0)
        return self.origin + self.unit * s, v


class MotionModel:
    """Planner queue, the running segment and the machine state. ``settings`` is the firmware's
    ``$`` table (read live: $100–$102 steps, $110–$112 rates, $120–$122 accelerations)."""

    def __init__(self, settings: dict, instant: bool, now: float, state: str = "Idle"):
        self.settings = settings
        self.instant = instant
        self.state = state
        self.pos = np.zeros(3)
        self.planned = np.zeros(3)  # where the planned blocks end
        self.planner: collections.deque[PlannedBlock] = collections.deque()
        self.segment: Segment | None = None
        self.events: list = []  # heap of (time, id, kind, argument)
        self._event_ids = itertools.count()
        self.last_stop = now
        self.hold_complete = self.hold_from_motion = False

    # ----------------------------------------------------------------- queries
    def position(self, now: float) -> np.ndarray:
        return self.pos.copy() if self.segment is None else self.segment.at(now)[0]

    def speed(self, now: float) -> float:
        """Units/min along the path now."""
        return 0.0 if self.segment is None else self.segment.at(now)[1] * 60.0

    def quantize(self, pos: np.ndarray) -> np.ndarray:
        """Whole steps ($100–$102)."""
        steps = np.array([self.settings[100 + i] for i in range(3)])
        return np.round(pos * steps) / steps

    def done(self) -> bool:
        return self.segment is None and not self.planner

    @property
    def moving(self) -> bool:
        """In a motion state (what a reset aborts with ALARM:3, or 6 while homing); a hold that
        is complete (Hold:0) is not."""
        if self.state == "Hold":
            return self.hold_from_motion and not self.hold_complete
        return self.state in ("Run", "Jog", "Home")

    def report_state(self) -> str:
        if self.state == "Hold":
            return f"Hold:{0 if self.hold_complete else 1}"
        return self.state

    def next_change(self) -> list[float]:
        times = [self.segment.end_time] if self.segment is not None else []
        return times + ([self.events[0][0]] if self.events else [])

    # ----------------------------------------------------------------- planning
    def plan(self, target: np.ndarray, rate: float, kind: str, now: float, event=None,
             event_at: float = 0.5, pause: float = 0.0) -> None:
        self.planner.append(PlannedBlock(target.copy(), rate, kind, now, event, event_at, pause))
        self.planned = target.copy()

    # ----------------------------------------------------------------- time
    def due_event(self, now: float) -> tuple | None:
        """The next (time, kind, argument) due by ``now``, with the motion advanced to it."""
        if not self.events or self.events[0][0] > now:
            return None
        t, _, kind, arg = heapq.heappop(self.events)
        self.advance(t)
        return t, kind, arg

    def advance(self, now: float) -> None:
        while True:
            seg = self.segment
            if seg is not None:
                if now < seg.end_time:
                    return
                self.pos, self.segment = seg.end.copy(), None
                self._finish_segment(seg.kind, seg.end_time)
            elif self.planner and self.state in RUNS_BLOCKS:
                self._start_block(max(self.planner[0].planned_at, self.last_stop))
            else:
                return

    def _start_block(self, t0: float) -> None:
        block = self.planner[0]
        delta = block.target - self.pos
        distance = float(np.linalg.norm(delta))
        self.state = _STATE_OF_KIND[block.kind]
        if block.pause > 0 and not self.instant:
            unit, profile = np.zeros(3), Profile.pause(block.pause)
        elif self.instant or distance < 1e-12:
            unit, profile = np.zeros(3), Profile(0.0, 0.0, 1.0, 0.0)
        else:
            unit = delta / distance
            rate = min(block.rate, self.axis_limit(unit, 110))
            profile = Profile.trapezoid(distance, rate / 60.0, self.axis_limit(unit, 120))
        self.segment = Segment(self.pos.copy(), unit, profile, t0, block.kind, block.target)
        if block.event is not None:
            when = t0 + profile.duration * block.event_at
            heapq.heappush(self.events, (when, next(self._event_ids), *block.event))
            block.event = None

    def _finish_segment(self, kind: str, t_end: float) -> None:
        self.last_stop = t_end
        if kind == "hold":
            self.hold_complete = True
            return
        if kind == "cancel":
            self.planner.clear()
            self.planned = self.pos.copy()
        else:
            self.planner.popleft()
        if not self.planner:
            self.state = "Idle"

    def axis_limit(self, unit: np.ndarray, base: int) -> float:
        """Largest rate (base 110) or acceleration (120) along ``unit`` that no axis exceeds."""
        return min(self.settings[base + i] / abs(u) for i, u in enumerate(unit) if abs(u) > 1e-12)

    # ----------------------------------------------------------------- stops
    def decelerate(self, now: float, kind: str) -> None:
        """Replace the running segment by a stop at its own acceleration (``hold``/``cancel``)."""
        seg = self.segment
        pos, speed = seg.at(now)
        accel = seg.profile.accel
        end = pos + seg.unit * (speed * speed / (2 * accel))
        self.segment = Segment(pos, seg.unit, Profile.stop(speed, accel), now, kind, end)

    def feed_hold(self, now: float) -> None:
        if self.state == "Jog":
            self.jog_cancel(now)
        elif self.state == "Run":
            self.decelerate(now, "hold")
            self.state, self.hold_complete, self.hold_from_motion = "Hold", False, True
        elif self.state == "Idle":
            self.state, self.hold_complete, self.hold_from_motion = "Hold", True, False

    def cycle_start(self, now: float) -> None:
        if self.state == "Hold" and self.hold_complete:  # ignored while still decelerating
            self.state = "Run" if self.planner else "Idle"
            self.hold_from_motion, self.last_stop = False, now
            self.advance(now)

    def jog_cancel(self, now: float) -> None:
        if self.state == "Jog" and self.segment is not None and self.segment.kind == "jog":
            self.decelerate(now, "cancel")

    def kill(self, now: float) -> None:
        """Stop the steppers where they are and forget every block (a reset or an alarm)."""
        self.pos = self.position(now)
        self.segment = None
        self.planner.clear()
        self.events.clear()
        self.planned = self.pos.copy()
        self.last_stop = now
        self.hold_complete = self.hold_from_motion = False
