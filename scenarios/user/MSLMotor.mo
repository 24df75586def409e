// The thesis's DC motor with rack and pinion (docs/explanation/thesis.md §6, Table 6.7) assembled from classes of the
// Modelica Standard Library 4.1.0: the armature circuit from Modelica.Electrical.Analog, the
// rotor's viscous friction and the rack and pinion from Modelica.Mechanics.Rotational.  The same
// parameters as models/blocks/motor.py (fidelity "full", rotor "lumped"): inertia-free, its
// rotor inertia J / rack^2 lumped into the mechanism's leg[i].m_act (scenarios/pid_step.yaml).
// Used by scenarios/pid_step_msl.yaml, with the library's directory in the scene's modelica_path.
package MSLDrive
  connector Flange "our causal bond to a leg: its extension rate and the force along it"
    Real v(unit = "m/s") "leg extension rate";
    flow Real f(unit = "N") "force on the motor from the leg";
  end Flange;

  model ArmatureResistance "Ohm's law on the MSL's one-port (Basic.Resistor carries an assert)"
    extends Modelica.Electrical.Analog.Interfaces.OnePort;
    parameter Modelica.Units.SI.Resistance R "resistance";
  equation
    v = R * i;
  end ArmatureResistance;

  model DCMotor "DC motor with rack and pinion from MSL components (thesis Table 6.7)"
    parameter Modelica.Units.SI.Resistance R = 0.574 "armature resistance (Table 6.7)";
    parameter Modelica.Units.SI.Inductance L = 0.251e-3 "armature inductance (Table 6.7: 0.251 mH)";
    parameter Modelica.Units.SI.ElectricalTorqueConstant kt = 0.0658572178311291
      "torque constant = back-EMF constant (145 rpm/V)";
    parameter Modelica.Units.SI.RotationalDampingConstant b = 86e-6
      "rotor viscous friction (Table 6.7: 86 uN m s/rad)";
    parameter Real rack(unit = "m/rad") = 0.05 "rack-and-pinion ratio: leg travel per shaft angle";
    input Real u(unit = "V") "armature voltage";
    Flange flange "the rack, bonded to a leg: its rate in, the force on it out";
    output Real i(unit = "A") "armature current";
    output Real torque(unit = "N.m") "electromagnetic torque kt i";
    Modelica.Electrical.Analog.Sources.SignalVoltage source "the driver's armature voltage";
    ArmatureResistance resistor(R = R) "armature resistance";
    Modelica.Electrical.Analog.Basic.Inductor inductor(L = L, i(start = 0, fixed = true)) "armature inductance";
    Modelica.Electrical.Analog.Basic.RotationalEMF emf(k = kt) "torque kt i, back-EMF kt w";
    Modelica.Electrical.Analog.Basic.Ground ground;
    Modelica.Mechanics.Rotational.Sources.LinearSpeedDependentTorque friction(tau_nominal = -b, w_nominal = 1,
      TorqueDirection = false) "rotor viscous friction: a load torque b w";
    Modelica.Mechanics.Rotational.Components.IdealGearR2T pinion(ratio = 1 / rack)
      "rack and pinion: shaft angle per leg travel [rad/m]";
    Modelica.Mechanics.Translational.Sources.Force leg "the leg's force on the rack";
  equation
    source.v = u;
    connect(source.p, resistor.p);
    connect(resistor.n, inductor.p);
    connect(inductor.n, emf.p);
    connect(emf.n, source.n);
    connect(source.n, ground.p);
    connect(emf.flange, friction.flange);
    connect(emf.flange, pinion.flangeR);
    connect(pinion.flangeT, leg.flange);
    der(leg.flange.s) = flange.v "the rack follows the leg";
    flange.f = leg.f "the leg's force on the rack is the motor's on the leg, reversed";
    i = inductor.i;
    torque = emf.tauElectrical;
  end DCMotor;
end MSLDrive;
