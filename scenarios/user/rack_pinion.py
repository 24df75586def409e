"""The rack-and-pinion gear of RackPinion.mo (Drive.RackPinion) written as a Python user block:
the same equations, for benchmarks/bench_userblocks.py and tests/test_user_blocks.py (two
formulations of one gear)."""
import casadi as ca

from models.user import BlockBuilder


def rack_pinion(integrator: str = "radau"):
    """Pinion and rotor inertia, viscous and smoothed Coulomb friction, compliant mesh to the leg."""
    b = BlockBuilder("rack_pinion", "rack and pinion: pinion and rotor inertia, viscous and smoothed Coulomb "
                                    "friction, compliant mesh")
    J = b.param("J", 1.45e-4, "kg.m2", "rotor and pinion inertia (Table 6.7: 1450 g cm2)", lower=0.0)
    bv = b.param("b", 86e-6, "N.m.s/rad", "viscous friction (Table 6.7: 86 uN m s/rad)", lower=0.0)
    Tc = b.param("Tc", 2e-3, "N.m", "Coulomb friction torque", lower=0.0)
    w_eps = b.param("w_eps", 0.1, "rad/s", "speed at which the Coulomb friction reaches tanh(1) of Tc", lower=1e-9)
    rack = b.param("rack", 0.05, "m/rad", "rack-and-pinion ratio: leg speed per shaft speed", lower=0.0)
    k = b.param("k", 1e6, "N/m", "mesh stiffness", lower=0.0)
    d = b.param("d", 500.0, "N.s/m", "mesh damping", lower=0.0)
    tau = b.input("shaft.tau", "N.m", "torque of the motor on the pinion")
    v = b.input("flange.v", "m/s", "leg extension rate")
    w = b.state("state.w", 0.0, "rad/s", "pinion speed")
    delta = b.state("state.delta", 0.0, "m", "mesh deflection: rack travel minus leg extension")
    friction = bv * w + Tc * ca.tanh(w / w_eps)
    f_mesh = k * delta + d * (rack * w - v)
    b.der(w, (tau - friction - rack * f_mesh) / J)
    b.der(delta, rack * w - v)
    b.output("shaft.w", w, "rad/s", "pinion speed")
    b.output("flange.f", f_mesh, "N", "force of the mesh on the leg")
    b.output("f_mesh", f_mesh, "N", "force of the mesh on the leg")
    b.output("friction", friction, "N.m", "friction torque")
    b.flange("shaft", "shaft.tau", "shaft.w", "flow_out")
    b.flange("flange", "flange.f", "flange.v", "effort_out")
    return b.build(integrator=integrator)


BLOCKS = {"rack_pinion": rack_pinion}
