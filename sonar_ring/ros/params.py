"""Declared, described and validated node parameters.

Each node lists its parameters as :class:`Param` entries; :func:`declare` declares
them all with a ``ParameterDescriptor`` (description, range, read-only) and
installs one ``add_on_set_parameters_callback`` that refuses a bad value with a
reason and keeps the old one.  rclpy itself enforces the numeric ranges and
read-only flags given in the descriptors; the callback adds choices and checks
that depend on the value (finite numbers, non-empty names).  :func:`file_values`
gives the values a node would start with from a parameters file, without a node
(``sonar-ring process``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import ParameterException
from rclpy.node import Node

from sonar_ring.geometry import read_config


class ParameterError(ValueError):
    """A start-up parameter value the node refuses (the text names the parameter and what it must be)."""


@dataclass(frozen=True)
class Param:
    """One parameter: name, default, description and constraints.

    ``low``/``high`` become the descriptor's range; ``choices`` restricts a
    string; ``read_only`` parameters can only be set at start-up (launch, YAML);
    ``check`` returns an error text for a bad value, or ``None``.
    """

    name: str
    default: object
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] = ()
    read_only: bool = False
    check: Callable[[object], str | None] | None = field(default=None, compare=False)

    def descriptor(self) -> ParameterDescriptor:
        """The ROS descriptor: description, additional constraints, range, read-only."""
        text = self.description
        constraints = f"one of: {', '.join(self.choices)}" if self.choices else ""
        descriptor = ParameterDescriptor(name=self.name, description=text, read_only=self.read_only,
                                         additional_constraints=constraints)
        if self.low is not None and self.high is not None:
            if isinstance(self.default, bool):
                raise TypeError(f"{self.name}: a boolean parameter takes no range")
            if isinstance(self.default, int):
                descriptor.integer_range = [IntegerRange(from_value=int(self.low), to_value=int(self.high), step=0)]
            else:
                descriptor.floating_point_range = [FloatingPointRange(from_value=float(self.low),
                                                                      to_value=float(self.high), step=0.0)]
        return descriptor

    def problem(self, value) -> str | None:
        """Why ``value`` is refused, or ``None`` when it is acceptable."""
        if isinstance(value, float) and not math.isfinite(value):
            return f"{self.name} must be finite, got {value}"
        if self.choices and value not in self.choices:
            return f"{self.name} must be one of {', '.join(self.choices)}, got {value!r}"
        if self.low is not None and isinstance(value, int | float) and not self.low <= value <= self.high:
            return f"{self.name} must be in [{self.low}, {self.high}], got {value}"
        return self.check(value) if self.check else None


def declare(node: Node, params: list[Param], on_change: Callable[[dict], None] | None = None) -> dict:
    """Declare ``params`` on ``node``; return their values by name.

    Start-up values (launch arguments, YAML) are validated like later changes:
    a bad one raises :class:`ParameterError` naming the parameter (also for
    what rclpy refuses: a value out of the descriptor's range or of the wrong
    type), so the node stops at launch with the reason rather than running
    misconfigured.  Later changes
    that pass validation are handed to ``on_change`` as ``{name: value}``.
    """
    by_name = {p.name: p for p in params}
    values = {}
    for p in params:
        try:
            value = node.declare_parameter(p.name, p.default, p.descriptor()).value
        except ParameterException as error:
            raise ParameterError(f"parameter {p.name}: {error}") from None
        reason = p.problem(value)
        if reason:
            raise ParameterError(f"parameter {reason}")
        values[p.name] = value

    def validate(changes) -> SetParametersResult:
        accepted = {}
        for change in changes:
            spec = by_name.get(change.name)
            if spec is None:
                continue
            reason = spec.problem(change.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
            accepted[change.name] = change.value
        values.update(accepted)
        if accepted and on_change:
            on_change(accepted)
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(validate)
    return values


def file_values(path, node_name: str, params: list[Param]) -> dict:
    """The values a node named ``node_name`` (root namespace) starts with, given a ROS parameters YAML file.

    ``path`` is a YAML path or the name of a shipped ``config/params`` file.
    The defaults of ``params``, overlaid with the file's ``/**`` section and
    then its ``/**/<node_name>``, ``<node_name>`` or ``/<node_name>`` section
    (the ``config/params/<layout>.yaml`` format).  Every value is checked as
    :func:`declare` checks it: the default's type (as rclpy does) and
    :meth:`Param.problem`.  Names the node does not declare are ignored, as the
    node ignores them.  A bad file or value raises :class:`ParameterError`
    naming the file and the parameter.
    """
    document, path = read_config(path, "params", ParameterError)
    values = {p.name: p.default for p in params}
    by_name = {p.name: p for p in params}
    for key in ("/**", f"/**/{node_name}", node_name, f"/{node_name}"):
        section = document.get(key)
        if section is None:
            continue
        given = section.get("ros__parameters") if isinstance(section, dict) else None
        if not isinstance(given, dict):
            raise ParameterError(f"{path}: section {key!r} has no ros__parameters mapping")
        for name, value in given.items():
            spec = by_name.get(name)
            if spec is None:
                continue
            if not _same_type(value, spec.default):
                raise ParameterError(f"{path}: parameter {name} must be like {spec.default!r}, got {value!r}")
            reason = spec.problem(value)
            if reason:
                raise ParameterError(f"{path}: parameter {reason}")
            values[name] = value
    return values


def _same_type(value, default) -> bool:
    """Whether rclpy would accept ``value`` for a parameter declared with ``default`` (no int/float mixing)."""
    if isinstance(default, list):
        return isinstance(value, list) and (not default or all(_same_type(v, default[0]) for v in value))
    return type(value) is type(default)
