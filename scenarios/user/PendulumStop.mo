model PendulumStop "a pendulum against a stop at its lowest point (impact with restitution)"
  parameter Real L(unit = "m") = 0.5 "rod length";
  parameter Real g(unit = "m/s2") = 9.81 "gravity";
  parameter Real e(unit = "1") = 0.7 "coefficient of restitution of the stop";
  Real theta(unit = "rad", start = 1, fixed = true) "angle from the downward vertical";
  Real omega(unit = "rad/s", start = 0, fixed = true) "angular rate";
  discrete Real impacts(unit = "1", start = 0) "impacts so far";
  discrete Real t_impact(unit = "s", start = 0) "time of the last impact";
equation
  der(theta) = omega;
  der(omega) = -g / L * sin(theta);
  when theta < 0 then
    reinit(omega, -e * pre(omega));
    impacts = pre(impacts) + 1;
    t_impact = time;
  end when;
end PendulumStop;
