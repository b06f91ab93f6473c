"""GRBL 1.1h's G-code parser for the firmware simulator: words → a checked block → modal state.

`GcodeParser.parse` validates a line as GRBL does (same ``error:N`` codes) without changing any
state; `GcodeParser.apply` then sets the modal state in GRBL's order (feed, units, coordinate
system, distance mode, motion mode) and returns the block's machine target, if it moves. The
parser also keeps the work coordinate systems (G54–G59, kept through resets like GRBL's EEPROM)
and the G92 offset. Simulated subset: G0 G1 G4 G10 L2/L20 G17 G20 G21 G53 G54-G59 G80 G90 G91 G92
G92.1 G94, M0-M9 M30 (accepted, no effect), F S T N; jog lines (``$J=``) through `parse_jog`.
"""

from __future__ import annotations

import dataclasses
import math
import re

import numpy as np

G_GROUPS = {0: 1, 1: 1, 80: 1, 4: 0, 10: 0, 53: 0, 92: 0, 92.1: 0, 17: 2, 90: 3, 91: 3, 94: 5}
G_GROUPS.update({20: 6, 21: 6, **{code: 12 for code in range(54, 60)}})
M_GROUPS = {0: 4, 1: 4, 2: 4, 30: 4, 3: 7, 4: 7, 5: 7, 7: 8, 8: 8, 9: 8}
NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)")
INCH = 25.4


class GcodeError(Exception):
    """A line GRBL refuses; ``code`` is the ``error:N`` number."""

    def __init__(self, code: int):
        super().__init__(code)
        self.code = code


def normalize_line(raw: str) -> str:
    """What GRBL keeps of a line: no whitespace, control characters or comments; upper case."""
    kept, in_comment = [], False
    for ch in raw:
        if in_comment:
            in_comment = ch != ")"
        elif ch == "(":
            in_comment = True
        elif ch == ";":
            break
        elif " " < ch < "\x7f":
            kept.append(ch.upper())
    return "".join(kept)


def split_words(line: str) -> list[tuple[str, float]]:
    """``"G1X10F600"`` -> ``[("G", 1.0), ("X", 10.0), ("F", 600.0)]``; GcodeError 1 or 2."""
    words, i = [], 0
    while i < len(line):
        if not "A" <= line[i] <= "Z":
            raise GcodeError(1)
        match = NUMBER.match(line, i + 1)
        if match is None:
            raise GcodeError(2)
        words.append((line[i], float(match.group())))
        i = match.end()
    return words


@dataclasses.dataclass(frozen=True)
class Block:
    """A checked G-code line. ``axes``: axis letter -> value in the line's units (not scaled)."""

    groups: dict
    values: dict
    axes: dict
    nonmodal: float | None
    motion: int  # the motion mode after this line (0, 1 or 80)
    scale: float  # 25.4 in G20, else 1
    feed: float  # units/min after this line, scaled to mm
    moving: bool  # plans a G0/G1 move

    @property
    def dwell(self) -> float | None:
        return self.values["P"] if self.nonmodal == 4 else None


@dataclasses.dataclass(frozen=True)
class Jog:
    """A checked ``$J=`` line: a move at ``feed`` (mm/min)."""

    axes: dict
    feed: float
    scale: float
    absolute: bool
    machine: bool


def parse_jog(text: str, inches: bool, absolute: bool) -> Jog:
    """Check the part of a jog line after ``$J=``; GcodeError with GRBL's code."""
    groups, values = {}, {}
    for letter, value in split_words(text):
        if letter == "G" and value in (20, 21, 53, 90, 91):
            group = G_GROUPS[int(value)]
            if group in groups:
                raise GcodeError(21)
            groups[group] = int(value)
        elif letter in "FXYZ":
            if letter in values:
                raise GcodeError(25)
            if letter == "F" and value < 0:
                raise GcodeError(4)
            values[letter] = value
        else:
            raise GcodeError(16)
    if "F" not in values:
        raise GcodeError(22)
    axes = {a: values[a] for a in "XYZ" if a in values}
    if not axes:
        raise GcodeError(26)
    scale = INCH if groups.get(6, 20 if inches else 21) == 20 else 1.0
    return Jog(axes, values["F"] * scale, scale, groups.get(3, 90 if absolute else 91) == 90,
               groups.get(0) == 53)


class GcodeParser:
    """Modal state and coordinate systems of GRBL's parser (see the module docstring)."""

    def __init__(self):
        self.coords = np.zeros((6, 3))  # G54..G59, kept through resets (EEPROM)
        self.reset()

    def reset(self) -> None:
        """What a soft reset restores: G0 G54 G17 G21 G90 G94, no G92 offset, feed 0."""
        self.motion, self.absolute, self.inches, self.feed = 0, True, False, 0.0
        self.coord_index, self.g92 = 0, np.zeros(3)

    def wco(self) -> np.ndarray:
        """(3,) work coordinate offset: the active G54–G59 origin plus G92."""
        return self.coords[self.coord_index] + self.g92

    def modal_report(self) -> str:
        """``[GC:…]`` for ``$G``."""
        units, dist = (20 if self.inches else 21), (90 if self.absolute else 91)
        return (f"[GC:G{self.motion} G{54 + self.coord_index} G17 G{units} G{dist} G94 M5 M9"
                f" T0 F{self.feed:.0f} S0]")

    def target(self, start: np.ndarray, axes: dict, scale: float, absolute: bool,
               machine: bool) -> np.ndarray:
        """(3,) machine target of ``axes`` from the planned position ``start``."""
        target = start.copy()
        wco = self.wco()
        for i, axis in enumerate("XYZ"):
            if axis in axes:
                value = axes[axis] * scale
                if machine:
                    target[i] = value
                elif absolute:
                    target[i] = value + wco[i]
                else:
                    target[i] += value
        return target

    def parse(self, line: str) -> Block:
        """Check a normalised line; GcodeError with GRBL's code. Changes nothing."""
        groups, mcodes, values = {}, {}, {}
        for letter, value in split_words(line):
            if letter in "GM":
                code = round(value, 1) if letter == "G" else value
                code = int(code) if code == int(code) else code
                table = G_GROUPS if letter == "G" else M_GROUPS
                if code not in table:
                    raise GcodeError(20)
                seen = groups if letter == "G" else mcodes
                if table[code] in seen:
                    raise GcodeError(21)
                seen[table[code]] = code
            elif letter in "FIJKLNPRSTXYZ":
                if letter in values:
                    raise GcodeError(25)
                if letter in "FNPST" and value < 0:
                    raise GcodeError(4)
                values[letter] = value
            else:
                raise GcodeError(20)
        nonmodal, motion_word = groups.get(0), groups.get(1)
        axis_command = nonmodal in (10, 92)
        if axis_command and motion_word is not None:
            raise GcodeError(24)
        axes = {a: values[a] for a in "XYZ" if a in values}
        if "N" in values and (values["N"] != int(values["N"]) or values["N"] > 9999999):
            raise GcodeError(27)
        if values.get("T", 0) > 255:
            raise GcodeError(38)
        units = groups.get(6, 20 if self.inches else 21)
        scale = INCH if units == 20 else 1.0
        motion = self.motion if motion_word is None else motion_word
        feed = values["F"] * scale if "F" in values else self.feed
        moving = bool(axes) and not axis_command and motion in (0, 1)
        if nonmodal == 53 and motion not in (0, 1):
            raise GcodeError(30)
        if axes and not axis_command and motion == 80:
            raise GcodeError(31)
        if motion_word in (0, 1) and not axes or axis_command and not axes:
            raise GcodeError(26)
        used = set("NFSTXYZ") | ({"P"} if nonmodal in (4, 10) else set())
        if nonmodal in (4, 10) and "P" not in values or nonmodal == 10 and "L" not in values:
            raise GcodeError(28)
        if nonmodal == 10:
            used.add("L")
            if values["L"] not in (2, 20):
                raise GcodeError(20)
            if int(values["P"]) > 6:
                raise GcodeError(29)
        if moving and motion == 1 and feed <= 0:
            raise GcodeError(22)
        if set(values) - used:
            raise GcodeError(36)
        return Block(groups, values, axes, nonmodal, motion, scale, feed, moving)

    def apply(self, block: Block, planned: np.ndarray) -> tuple[np.ndarray, float] | None:
        """Set the modal state and the G92 offset; (machine target, rate) if the block moves.

        planned : (3,) machine position at the end of the planned moves. G10 is not applied
        here: it waits for motion to end (`set_origin`)."""
        groups = block.groups
        self.feed = block.feed
        self.inches = block.scale != 1.0
        if 12 in groups:
            self.coord_index = groups[12] - 54
        if 3 in groups:
            self.absolute = groups[3] == 90
        if 1 in groups:
            self.motion = groups[1]
        if block.nonmodal in (92, 92.1):
            for i, axis in enumerate("XYZ"):
                if block.nonmodal == 92.1:
                    self.g92[i] = 0.0
                elif axis in block.axes:
                    self.g92[i] = planned[i] - self.coords[self.coord_index, i]
                    self.g92[i] -= block.axes[axis] * block.scale
        if not block.moving:
            return None
        target = self.target(planned, block.axes, block.scale, self.absolute,
                             machine=block.nonmodal == 53)
        return target, math.inf if block.motion == 0 else block.feed

    def set_origin(self, block: Block, position: np.ndarray) -> None:
        """G10 L2/L20: a coordinate system's origin, with the axes still at ``position``."""
        values = block.values
        index = int(values["P"]) - 1 if values["P"] >= 1 else self.coord_index
        for i, axis in enumerate("XYZ"):
            if axis in block.axes:
                value = block.axes[axis] * block.scale
                if values["L"] == 20:
                    value = position[i] - self.g92[i] - value
                self.coords[index, i] = value
