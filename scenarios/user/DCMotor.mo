// The thesis's DC motor with rack and pinion (docs/explanation/thesis.md §6, Table 6.7) written in Modelica:
// the same equations as models/blocks/motor.py (fidelity "full", rotor "lumped").
package Motors
  type Voltage = Real(unit = "V");
  type Current = Real(unit = "A");
  type Resistance = Real(unit = "Ohm");
  type Inductance = Real(unit = "H");
  type Force = Real(unit = "N");
  type Velocity = Real(unit = "m/s");
  type Torque = Real(unit = "N.m");
  type AngularVelocity = Real(unit = "rad/s");

  connector Flange "translational power port: leg speed and force"
    Velocity v "leg extension rate (rack speed)";
    flow Force f "force on the leg, positive extending";
  end Flange;

  model DCMotor "DC motor with rack and pinion (full, rotor lumped; thesis Table 6.7)"
    parameter Resistance R(min = 0) = 0.574 "armature resistance (Table 6.7)";
    parameter Real kt(unit = "N.m/A", min = 0) = 0.0658572178311291 "torque constant = back-EMF constant [V s/rad]";
    parameter Real J(unit = "kg.m2", min = 0) = 1.45e-4 "rotor inertia (Table 6.7: 1450 g cm2)";
    parameter Real b(unit = "N.m.s/rad", min = 0) = 86e-6 "rotor viscous friction (Table 6.7: 86 uN m s/rad)";
    parameter Real rack(unit = "m/rad", min = 0) = 0.05 "rack-and-pinion ratio: leg speed per shaft speed";
    parameter Inductance L(min = 0) = 0.251e-3 "armature inductance (Table 6.7: 0.251 mH)";
    input Voltage u "armature voltage";
    Flange flange "the rack, bonded to a leg";
    output Current i(start = 0, fixed = true) "armature current";
    output Torque torque "electromagnetic torque kt i";
    output AngularVelocity w "shaft speed";
    output Real m_reflected(unit = "kg") "rotor inertia seen at the leg, J/rack^2: lump into the mechanism's leg[i].m_act";
  equation
    w = flange.v / rack;
    L * der(i) = u - R * i - kt * w;
    torque = kt * i;
    flange.f = -(torque - b * w) / rack;
    m_reflected = J / rack ^ 2;
  end DCMotor;
end Motors;
