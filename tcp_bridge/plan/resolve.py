"""A request resolved once: its row of the command table, its axis and its value.

:func:`resolve` runs on the event loop, in the order requests arrived from every
connection (one MasterMACS serves one request at a time, and so does the
bridge's resolution). It checks everything the request says (axis, command,
R/W rights, value) and raises every :class:`~tcp_bridge.errors.InvalidCommand`
(answered CAN) that does not depend on the axis's state; the handlers of
:mod:`.reads`, :mod:`.writes` and :mod:`.moves` then plan it against the state
that all earlier requests left (:class:`~tcp_bridge.plan.axis.AxisRuntime`),
and fix every value they use.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Final, Mapping, Optional

from ..errors import InvalidCommand
from ..tables.axes import parameter_spec
from ..tables.commands import CommandSpec, resolve as resolve_spec, rule_of
from ..tables.units import Number, parse_value
from ..wire import ReadRequest, Request

if TYPE_CHECKING:
    from .axis import AxisRuntime

GLOBAL_COMMANDS: Final = frozenset({91, 99})  # answered for any axis number


@dataclass(frozen=True)
class Resolved:
    """What a request means, decided once."""

    request: Request
    spec: CommandSpec
    rule: str  # the handler's name (tcp_bridge.tables.commands.rule_of)
    axis: Optional["AxisRuntime"]  # None for the global commands 91 and 99
    value: Optional[Number] = None  # a write's value in user units

    @property
    def reading(self) -> bool:
        return isinstance(self.request, ReadRequest)

    def invalid(self, why: str) -> InvalidCommand:
        """CAN for this request, with its full header."""
        r = self.request
        return InvalidCommand(why, axis=r.axis, kind=r.kind, cmd=r.cmd)


def resolve(request: Request, axes: Mapping[int, "AxisRuntime"]) -> Resolved:
    """Check ``request`` against the command and axis tables; CAN if it is not valid."""
    spec = resolve_spec(request)
    rule = rule_of(spec)
    if request.cmd in GLOBAL_COMMANDS:
        axis = None
    else:
        axis = axes.get(request.axis)
        if axis is None:
            raise InvalidCommand(f"axis {request.axis} is not configured",
                                 axis=request.axis, kind=request.kind, cmd=request.cmd)
    if isinstance(request, ReadRequest):
        return Resolved(request, spec, rule, axis)
    try:
        # 19 is a parameter whose row has its own rule; its value is parsed as one.
        value = parse_value(parameter_spec(19) if spec.number == 19 else spec, request.value)
    except InvalidCommand as exc:
        raise InvalidCommand(str(exc), axis=request.axis, kind=request.kind,
                             cmd=request.cmd) from exc
    return Resolved(request, spec, rule, axis, value)


__all__ = ["GLOBAL_COMMANDS", "Resolved", "resolve"]
