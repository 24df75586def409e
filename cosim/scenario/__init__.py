"""Scenes: YAML files that assemble components into a co-simulation, checked before anything runs.

Format (every key but ``components`` and ``connections`` optional; lines starting ``#`` are comments)::

    name: pid_step
    description: free text
    include: base.yaml          # another scene, merged under this one (paths relative to this file)
    start_time: 0.0             # [s] (default: the FMUs' DefaultExperiment, else 0)
    stop_time: 5.0              # [s] (default: the FMUs' DefaultExperiment)
    components:                 # a mapping name -> spec (or a list of specs with a 'name:' key)
      mech:   {model: mechanism, fidelity: rigid, options: {config: cross_leg}, params: {leg[1].m_act: 0.058}}
      pid1:   {model: pid, params: {Kp: 30, Ki: 80, Kd: 20, u_max: 12}}
      plant:  {fmu: plant.fmu, params: {k: 1e4}, start: {x: 0.1}}    # any external FMU
    connections:
      - target.leg[1].s -> pid1.setpoint        # signal: output -> input
      - stair.counter -> plant.u as Float64     # an explicit type conversion (cosim.slaves.types)
      - motor1.flange <-> mech.leg[1]           # power bond between two flanges
      - mech.leg[1].s -> pid1.measurement * 1000 + 0.5   # signal through a linear transformation
    master: {algorithm: gauss_seidel, step: 1e-3, order: [target, pid1, motor1, mech],
             engine: auto, output_interval: 1e-3}
    outputs: ["mech.platform.*", "mech.leg[*].f"]   # fnmatch over "component.variable"
    guards: {stroke: stop, singularity: warn}       # physical guards (cosim.run.row_guards); all "stop" by default

Component spec: ``model`` (a name of :func:`models.blocks.catalog`) with optional ``fidelity``
and ``options`` (construction options of :func:`models.blocks.make`), or ``fmu`` (a path);
``params`` sets parameters by name (structural ones go to ``make``, the others are set on the
instance at start-up, so one compiled FMU serves every value); ``start`` sets start values of
inputs and states (for an FMU: inputs and variables with initial = exact or approx; parameters
and FMI 3.0 structural parameters go under ``params``, any FMI type, arrays as lists); ``fmi`` picks the FMI version of a built FMU ("2.0" default, or "3.0").
``rollback: false`` makes the master treat the component as one that cannot save and restore its
state (as hardware): ``adaptive`` refuses it, ``ecco`` and the fixed-step algorithms run it.

A bond ``a.p <-> b.q`` joins two flanges: the side whose flange computes the effort
(``effort_out``) feeds its effort output to the other side's effort input, and the other side
feeds its flow output back; both sides must differ in causality.

Includes merge deeply: mappings key by key (the including file wins; ``null`` deletes), a
component whose ``model``/``fmu`` changes is replaced whole, ``connections`` extend the included
ones (a connection into an input, or a bond on a flange, that the included scene already feeds
replaces it), other lists are replaced.  ``--set path=value`` overrides work the same way:
``master.step=5e-4``, ``components.pid1.params.Kp=40``, ``components.mech.params.leg[1].m_act=0.06``
(everything after ``params.`` or ``start.`` is one variable name).

Validation collects every problem (file, line, message with the closest valid name) and raises
:class:`SceneError` listing them all; warnings (e.g. an unconnected input without a start value)
are kept on :attr:`Scene.warnings`.

Package map (the public names are re-exported here: ``from cosim.scenario import X``):

``yamlfile``     YAML with line numbers (:class:`YMap`, :class:`YList`, :func:`read_yaml`)
``merge``        includes and merging (:func:`load_raw`, :func:`merge`)
``overrides``    ``--set`` overrides (:func:`parse_set`, :func:`apply_overrides`, :func:`plain`)
``keys``         the keys a scene may use
``problems``     :class:`Problem`, :class:`SceneError`, :func:`suggest`
``model``        the validated scene: :class:`Scene`, :class:`Component`, :class:`Connection`,
                 :class:`MasterSettings`
``catalog``      the model catalog, loaded lazily
``checker``, ``check_components``, ``check_connections``, ``check_master``
                 validation, one mixin per section of the scene
``validate``     :func:`validate`: a merged tree to a :class:`Scene`
``loading``      :func:`load` (file, includes, overrides) and :func:`from_dict`
"""
from __future__ import annotations

from .catalog import default_catalog, make_block
from .keys import COMPONENT_KEYS, ENGINES, FMI_VERSIONS, INPUT_MODES, MASTER_KEYS, TOP_KEYS
from .loading import from_dict, load
from .merge import load_raw, merge, split_transform
from .model import Component, Connection, MasterSettings, Scene
from .overrides import apply_overrides, parse_set, plain
from .problems import Loc, Problem, SceneError, suggest
from .validate import validate
from .yamlfile import MAX_YAML_NODES, YList, YMap, _display, read_yaml

__all__ = ["COMPONENT_KEYS", "ENGINES", "FMI_VERSIONS", "INPUT_MODES", "MASTER_KEYS", "MAX_YAML_NODES", "TOP_KEYS",
           "Component", "Connection", "Loc", "MasterSettings", "Problem", "Scene", "SceneError", "YList", "YMap",
           "_display", "apply_overrides", "default_catalog", "from_dict", "load", "load_raw", "make_block", "merge",
           "parse_set", "plain", "read_yaml", "split_transform", "suggest", "validate"]
