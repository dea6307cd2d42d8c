"""Declared, described and validated node parameters.

Each node lists its parameters as :class:`Param` entries; :func:`declare` declares
them all with a ``ParameterDescriptor`` (description, range, read-only) and
installs one ``add_on_set_parameters_callback`` that refuses a bad value with a
reason and keeps the old one.  rclpy itself enforces the numeric ranges and
read-only flags given in the descriptors; the callback adds choices and checks
that depend on the value (finite numbers, non-empty names).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node


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
    a bad one raises ``ValueError`` naming the parameter, so the node stops at
    launch with the reason rather than running misconfigured.  Later changes
    that pass validation are handed to ``on_change`` as ``{name: value}``.
    """
    by_name = {p.name: p for p in params}
    values = {}
    for p in params:
        value = node.declare_parameter(p.name, p.default, p.descriptor()).value
        reason = p.problem(value)
        if reason:
            raise ValueError(f"parameter {reason}")
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
