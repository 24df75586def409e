// A rack-and-pinion gear with viscous and smoothed Coulomb friction between a DC motor's shaft
// and a leg, and the thesis's DC motor (docs/explanation/thesis.md §6, Table 6.7) with a rotational shaft: the
// components of scenarios/gear_step.yaml.  Types as Modelica.Units.SI declares them.
package Drive
  type Voltage = Real(unit = "V");
  type Current = Real(unit = "A");
  type Force = Real(unit = "N");
  type Velocity = Real(unit = "m/s");
  type Torque = Real(unit = "N.m");
  type AngularVelocity = Real(unit = "rad/s");

  connector Shaft "rotational power port"
    AngularVelocity w "shaft speed";
    flow Torque tau "torque on the component";
  end Shaft;

  connector Flange "translational power port"
    Velocity v "leg extension rate";
    flow Force f "force on the component";
  end Flange;

  model Motor "DC motor (the thesis, Table 6.7), inertia-free: its rotor inertia is the gear's"
    parameter Real R(unit = "Ohm", min = 0) = 0.574 "armature resistance (Table 6.7)";
    parameter Real kt(unit = "N.m/A", min = 0) = 0.0658572178311291 "torque constant = back-EMF constant";
    parameter Real L(unit = "H", min = 0) = 0.251e-3 "armature inductance (Table 6.7)";
    input Voltage u "armature voltage";
    Shaft shaft "the motor shaft";
    output Current i(start = 0, fixed = true) "armature current";
  equation
    L * der(i) = u - R * i - kt * shaft.w;
    shaft.tau = -kt * i;
  end Motor;

  model RackPinion "rack and pinion: pinion and rotor inertia, viscous and smoothed Coulomb friction, compliant mesh"
    parameter Real J(unit = "kg.m2", min = 0) = 1.45e-4 "rotor and pinion inertia (Table 6.7: 1450 g cm2)";
    parameter Real b(unit = "N.m.s/rad", min = 0) = 86e-6 "viscous friction (Table 6.7: 86 uN m s/rad)";
    parameter Torque Tc(min = 0) = 2e-3 "Coulomb friction torque";
    parameter AngularVelocity w_eps(min = 1e-9) = 0.1 "speed at which the Coulomb friction reaches tanh(1) of Tc";
    parameter Real rack(unit = "m/rad", min = 0) = 0.05 "rack-and-pinion ratio: leg speed per shaft speed";
    parameter Real k(unit = "N/m", min = 0) = 1e6 "mesh stiffness";
    parameter Real d(unit = "N.s/m", min = 0) = 500 "mesh damping";
    Shaft shaft "to the motor";
    Flange flange "to the leg";
    Real w(unit = "rad/s", start = 0) "pinion speed";
    Real delta(unit = "m", start = 0) "mesh deflection: rack travel minus leg extension";
    output Force f_mesh "force of the mesh on the leg";
    output Torque friction "friction torque";
  equation
    shaft.w = w;
    friction = b * w + Tc * tanh(w / w_eps);
    J * der(w) = shaft.tau - friction - rack * f_mesh;
    der(delta) = rack * w - flange.v;
    f_mesh = k * delta + d * (rack * w - flange.v);
    flange.f = -f_mesh;
  end RackPinion;
end Drive;
