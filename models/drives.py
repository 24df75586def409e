"""Leg drives as straight force-speed lines at their rated voltage (used by the planner, the
motion check and the feedforward of :mod:`models.blocks.task`).

A drive's quasi-static voltage is ``u = alpha F + beta v`` [V] for leg force F [N] at leg speed
v [m/s]: for a DC motor with a rack, ``alpha = R rack / kt`` and ``beta = kt / rack + R b /
(kt rack)`` (back-EMF and rotor friction; the armature inductance's ``L di/dt`` is neglected,
0.44 ms for Table 6.7's motor); for the Firgelli actuator the datasheet's line through its
no-load speed and its force rating.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Drive:
    """A leg actuator's straight force-speed line at its rated voltage: ``u = alpha F + beta v``.

    ``U`` [V] rated voltage; ``F_stall`` [N] force at zero speed and ``U``; ``v_nl`` [m/s] speed at
    no load and ``U``; ``F_max`` [N] the largest force it may carry (current or datasheet limit).
    """

    name: str
    U: float
    F_stall: float
    v_nl: float
    F_max: float

    @property
    def alpha(self) -> float:
        """Volts per newton [V/N]."""
        return self.U / self.F_stall

    @property
    def beta(self) -> float:
        """Volts per metre per second (back-EMF and friction) [V s/m]."""
        return self.U / self.v_nl

    @property
    def power(self) -> float:
        """Largest mechanical power [W] on the line at ``U``: ``F_stall v_nl / 4``."""
        return self.F_stall * self.v_nl / 4.0

    def voltage(self, F, v):
        """Quasi-static voltage [V] for leg force ``F`` [N] at leg speed ``v`` [m/s]."""
        return self.alpha * F + self.beta * v


def dc_drive(name: str, U: float, R: float, kt: float, b: float, rack: float, i_max: float) -> Drive:
    """The line of a DC motor (resistance R [Ohm], constant kt [N m/A], friction b [N m s/rad])
    driving a rack of ``rack`` [m/rad], current limited to ``i_max`` [A]."""
    alpha = R * rack / kt
    beta = kt / rack + R * b / (kt * rack)
    return Drive(name, U, U / alpha, U / beta, i_max * kt / rack)


#: The Table 6.7 motor (thesis.md §6) as the dc_motor block declares it: R [Ohm], kt [N m/A] (145 rpm/V),
#: b [N m s/rad], rack [m/rad]; the 12 V rating and the driver's 30 A peak (models.blocks.motor;
#: tests/test_task.py checks that the two agree).
TABLE_6_7 = {"R": 0.574, "kt": 60.0 / (2 * math.pi * 145.0), "b": 86e-6, "rack": 0.05}
U_RATED, I_PEAK = 12.0, 30.0

#: The Table 6.7 motor of the simulated loop, and the rig's Firgelli FA-200-L-12 (thesis.md §7:
#: 12 V, 20.32 mm/s, 890 N).
DRIVES = {
    "table67": dc_drive("table67", U_RATED, TABLE_6_7["R"], TABLE_6_7["kt"], TABLE_6_7["b"], TABLE_6_7["rack"], I_PEAK),
    "fa200": Drive("fa200", 12.0, 890.0, 0.02032, 890.0),
}


