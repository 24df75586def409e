"""Validation of connections and bonds: endpoints, types, unconnected inputs, algebraic loops."""
from __future__ import annotations

import dataclasses

from models.units import scaled
from models.units import text as unit_text

from ..slaves.types import TYPES, canonical, conversion, display
from ..master import ALGORITHMS, find_algebraic_loop
from ..slaves.description import Variable
from .checker import Checker
from .merge import _ARROW, _AS, split_transform
from .model import Component, Connection
from .problems import Loc, suggest
from .yamlfile import YList


#: Catalog models whose signals carry whatever unit they are given (their declared "1" is no
#: dimension): a connection to or from one is not unit-checked.
UNIT_AGNOSTIC = ("sum",)


class ConnectionChecks(Checker):
    """Checks of the ``connections:`` section."""

    def endpoint(self, text: str, comps: dict[str, Component], where: Loc, side: str) -> tuple[str, str] | None:
        name, dot, var = text.partition(".")
        if not dot or not var:
            self.err(where, f"{side} {text!r} must be component.variable (e.g. mech.leg[1].s)")
            return None
        if name not in comps:
            if name not in self.refused:  # a refused component's problem is reported once, where it is declared
                self.err(where, f"unknown component {name!r} in {text!r}{suggest(name, comps)}")
            return None
        return name, var

    def signal(self, src: str, sv: str, dst: str, dv: str, comps: dict[str, Component], where: Loc,
               bond: str | None = None, as_type: str | None = None) -> Connection | None:
        a, b = comps[src].description.variables, comps[dst].description.variables
        ok = True
        for comp, var, vs in ((src, sv, a), (dst, dv, b)):
            if var not in vs:
                flange = comps[comp].description.flange(var)
                if flange is not None:
                    self.err(where, f"{comp}.{var} is a flange; join flanges with '<->' (a bond), not '->'")
                else:
                    cands = [n for n in vs if vs[n].causality in ("input", "output")]
                    self.err(where, f"component {comp!r} ({comps[comp].label}) has no variable {var!r}"
                                    f"{suggest(var, cands)}")
                ok = False
        if not ok:
            return None
        ca_, cb = a[sv].causality, b[dv].causality
        lhs, rhs = f"{src}.{sv}", f"{dst}.{dv}"
        if ca_ == "output" and cb == "output":
            self.err(where, f"connects two outputs ({lhs} and {rhs}); a connection goes from an output to an input")
            return None
        if ca_ == "input" and cb == "input":
            self.err(where, f"connects two inputs ({lhs} and {rhs}); a connection goes from an output to an input")
            return None
        if ca_ == "input" and cb == "output":
            self.err(where, f"is reversed: {lhs} is an input and {rhs} an output; write '{rhs} -> {lhs}'")
            return None
        if ca_ != "output":
            self.err(where, f"{lhs} is a{'n' if ca_[0] in 'aeiou' else ''} {ca_}, not an output; "
                            f"only outputs can feed a connection")
            return None
        if cb != "input":
            hint = f"; set it under components.{dst}.params" if cb == "parameter" else ""
            self.err(where, f"{rhs} is a{'n' if cb[0] in 'aeiou' else ''} {cb}, not an input{hint}")
            return None
        if not self.types_agree(comps[src], a[sv], comps[dst], b[dv], where, as_type):
            return None
        return Connection(src, sv, dst, dv, bond, where, as_type)

    def types_agree(self, ca: Component, va: Variable, cb: Component, vb: Variable, where: Loc,
                    as_type: str | None) -> bool:
        """Equal types and sizes, or an allowed conversion asked for with ``as TYPE`` (see
        :mod:`cosim.slaves.types`); otherwise report the types and the remedy."""
        lhs, rhs = f"{ca.name}.{va.name}", f"{cb.name}.{vb.name}"
        ta, tb = display(va.type, ca.description.fmi_version), display(vb.type, cb.description.fmi_version)
        for comp, var, t in ((ca, va, ta), (cb, vb, tb)):
            if var.type not in TYPES:
                self.err(where, f"{comp.name}.{var.name} is a {t} variable; {t} variables cannot be connected")
                return False
        if va.shape != vb.shape:
            shape = lambda v: "a scalar" if not v.shape else "an array of shape " + "x".join(map(str, v.shape))
            self.err(where, f"size mismatch: {lhs} is {shape(va)} ({ta}) but {rhs} is {shape(vb)} ({tb})")
            return False
        if as_type is not None and canonical(as_type) != vb.type:
            self.err(where, f"'as {as_type}' must name the type of {rhs}, which is {tb}")
            return False
        if va.type == vb.type:
            return True
        why = conversion(va.type, vb.type)
        if why is not None:
            self.err(where, f"type mismatch: {lhs} is {ta} but {rhs} is {tb}, and {ta} -> {tb} is no allowed "
                            f"conversion: {why}")
            return False
        if as_type is None:
            self.err(where, f"type mismatch: {lhs} is {ta} but {rhs} is {tb}; to convert, write "
                            f"'{lhs} -> {rhs} as {tb}'")
            return False
        return True

    def units_agree(self, comps: dict[str, Component], c: Connection, where: Loc) -> bool:
        """Modelica's rule for a connection: both ends in compatible units.  Refused: a different
        dimension (``m/s -> m``), or the same one at another scale (``mm -> m``: the master passes
        the number, so the factor is named).  Not checked: an end without a unit or with a symbol
        not known to :mod:`models.units`, a connection with a factor or offset (it converts, and its
        numbers carry no unit), and the ends of a :data:`UNIT_AGNOSTIC` block (a sum carries the
        unit of what it sums, as Modelica's ``Add`` declares none)."""
        if c.factor != 1.0 or c.offset != 0.0:
            return True
        if comps[c.src].model in UNIT_AGNOSTIC or comps[c.dst].model in UNIT_AGNOSTIC:
            return True
        ua = comps[c.src].description.variables[c.src_var].unit
        ub = comps[c.dst].description.variables[c.dst_var].unit
        a, b = scaled(ua), scaled(ub)
        if a is None or b is None or ua.strip() == ub.strip():
            return True
        lhs, rhs = f"{c.src}.{c.src_var} [{ua}]", f"{c.dst}.{c.dst_var} [{ub}]"
        if a[1] != b[1]:
            self.err(where, f"incompatible units: {lhs} -> {rhs} ({unit_text(a[1])} is not {unit_text(b[1])}); "
                            f"connect a signal of the input's unit, or convert with '* FACTOR' where a ratio "
                            f"is meant")
            return False
        ratio = a[0] / b[0]
        if abs(ratio - 1.0) > 1e-12:
            self.err(where, f"units differ in scale: {lhs} -> {rhs}; the master passes the number as it is: "
                            f"write '{c.src}.{c.src_var} -> {c.dst}.{c.dst_var} * {ratio:.12g}'")
            return False
        return True

    def connections(self, comps: dict[str, Component]) -> tuple[list[Connection], list[tuple]]:
        node = self.tree.get("connections", YList())
        if not isinstance(node, list):
            self.err(self.tree.loc("connections"), "connections must be a list of 'a.out -> b.in' or "
                                                   "'a.flange <-> b.flange' strings")
            return [], []
        conns: list[Connection] = []
        bonds: list[tuple] = []
        fed: dict[tuple[str, str], Connection] = {}
        bonded: dict[tuple[str, str], Loc] = {}
        for i, item in enumerate(node):
            where = node.loc(i) if isinstance(node, YList) else self.tree.loc("connections")
            as_type = None
            if isinstance(item, str) and (conv := _AS.match(item)):
                item, as_type = conv.group(1), conv.group(2)
            affine = split_transform(item) if isinstance(item, str) else (item, 1.0, 0.0)
            if affine is None:
                self.err(where, f"connection {item!r}: a transformation reads '* FACTOR + OFFSET' with numbers, "
                                f"e.g. 'a.y -> b.u * 0.001 + 0.5'")
                continue
            item, factor, offset = affine
            m = _ARROW.match(item) if isinstance(item, str) else None
            if m and as_type is not None and m.group(2) != "->":
                self.err(where, f"'as {as_type}' converts a signal ('a.out -> b.in as TYPE'), not a bond")
                continue
            if not m:
                self.err(where, f"connection {item!r} must read 'a.out -> b.in' (a signal) or "
                                f"'a.flange <-> b.flange' (a power bond)")
                continue
            lhs, arrow, rhs = m.groups()
            a = self.endpoint(lhs, comps, where, "left side")
            b = self.endpoint(rhs, comps, where, "right side")
            if a is None or b is None:
                continue
            new: list[Connection] = []
            if arrow == "->":
                c = self.signal(*a, *b, comps, where, as_type=as_type)
                if c is not None:
                    new.append(dataclasses.replace(c, factor=factor, offset=offset))
            elif factor != 1.0 or offset != 0.0:
                self.err(where, f"bond {lhs} <-> {rhs}: a power bond takes no transformation")
                continue
            else:
                fa, fb = comps[a[0]].description.flange(a[1]), comps[b[0]].description.flange(b[1])
                bad = False
                for (cn, fn), fl in ((a, fa), (b, fb)):
                    if fl is None:
                        names = [f.name for f in comps[cn].description.flanges]
                        kind = f" ({fn!r} is a variable, not a flange)" if fn in comps[cn].description.variables else ""
                        self.err(where, f"component {cn!r} ({comps[cn].label}) has no flange {fn!r}{kind}"
                                        f"{suggest(fn, names)} (flanges: {', '.join(names) or 'none'})")
                        bad = True
                    elif (cn, fn) in bonded:
                        self.err(where, f"flange {cn}.{fn} is already bonded (line {bonded[(cn, fn)][1]}); "
                                        f"a flange takes one bond")
                        bad = True
                if bad:
                    continue
                if fa.causality == fb.causality:
                    what = "effort" if fa.causality == "effort_out" else "flow"
                    why = "".join(f"; {cn}.{fn} cannot: {fl.why}" for (cn, fn), fl in ((a, fa), (b, fb)) if fl.why)
                    self.err(where, f"bond {lhs} <-> {rhs}: both flanges compute the {what} ({fa.causality}); "
                                    f"one side must take it as input{why}")
                    continue
                eff, flo = ((a, fa), (b, fb)) if fa.causality == "effort_out" else ((b, fb), (a, fa))
                label = f"{lhs} <-> {rhs}"
                for c in (self.signal(eff[0][0], eff[1].effort, flo[0][0], flo[1].effort, comps, where, label),
                          self.signal(flo[0][0], flo[1].flow, eff[0][0], eff[1].flow, comps, where, label)):
                    if c is not None:
                        new.append(c)
                if len(new) == 2:
                    bonds.append((a[0], a[1], b[0], b[1]))
                    bonded[a] = bonded[b] = where
            for c in new:
                self.units_agree(comps, c, where)  # reported; the connection still counts for the checks below
                key = (c.dst, c.dst_var)
                if key in fed:
                    self.err(where, f"input {c.dst}.{c.dst_var} is already connected (from "
                                    f"{fed[key].src}.{fed[key].src_var}, line {fed[key].where[1]}); an input takes "
                                    f"one source")
                    continue
                fed[key] = c
                conns.append(c)
        return conns, bonds

    def unconnected(self, comps: dict[str, Component], conns: list[Connection]) -> None:
        fed = {(c.dst, c.dst_var) for c in conns}
        for comp in comps.values():
            for u in comp.description.of("input"):
                if (comp.name, u) not in fed and u not in comp.start:
                    var = comp.description.variables[u]
                    start = var.start if var.start is not None else var.raw_start
                    self.warn(comp.where, f"input {comp.name}.{u} is not connected and has no start value in the "
                                          f"scene; it keeps its default start value {start if start is not None else 0.0}")

    def algebraic_loops(self, comps: dict[str, Component], conns: list[Connection], algorithm: str | None = None) -> None:
        cls = ALGORITHMS.get(algorithm)  # None: no algorithm named (auto), or one unknown (reported elsewhere)
        if cls is not None and cls.solves_algebraic_loops:
            return  # the algorithm iterates each step to a consistent solution of the loop
        cyc = algebraic_loop(comps, conns)
        if cyc:
            text = " -> ".join(f"{c}.{v}" for c, v in cyc)
            first = next((c for c in conns if (c.src, c.src_var) in cyc and (c.dst, c.dst_var) in cyc), conns[0])
            if cls is not None and cls.delays_algebraic_loops:
                self.note(first.where, f"algebraic loop (a cycle of direct feedthrough): {text}; {algorithm} runs it "
                                       f"with its one-step coupling delay (each output on the loop is read at t_k "
                                       f"from inputs of t_k-1), as libcosim and FMPy do")
                return
            self.err(first.where, f"algebraic loop (a cycle of direct feedthrough): {text}; break it with a "
                                  f"component that has a state on the path (e.g. a motor with inductance, "
                                  f"fidelity full, or a continuous PID), or use master.algorithm: iterative, "
                                  f"which solves the loop within each step")

    # master, time, outputs ------------------------------------------------------------------------------


def algebraic_loop(comps: dict[str, Component], conns: list[Connection]) -> list[tuple[str, str]] | None:
    """A cycle of direct feedthrough through the connections, as (component, variable) ports, or None."""
    edges = [((c.src, c.src_var), (c.dst, c.dst_var)) for c in conns]
    for comp in comps.values():
        for y, us in comp.description.feedthrough.items():
            edges += [((comp.name, u), (comp.name, y)) for u in us]
    return find_algebraic_loop(edges)
