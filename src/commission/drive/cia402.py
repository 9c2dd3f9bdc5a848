"""CiA 402 (IEC 61800-7-201) drive profile: states, modes, controlword, statusword.

The vocabulary of the standard, shared by every backend (which drives a real
drive through it) and by the simulated drive (which implements it). Only what
the standard fixes lives here; how a state is reached over a link is the
backend's business.
"""

from __future__ import annotations

from enum import Enum, IntEnum


class State(Enum):
    """Power drive system states (CiA 402 §6.1), decoded from the statusword."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


class Mode(IntEnum):
    """Modes of operation (object 0x6060 / 0x6061)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    PROFILE_TORQUE = 4
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


class Command(IntEnum):
    """Controlword values of the device-control commands (object 0x6040)."""

    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    DISABLE_OPERATION = 0x0007
    FAULT_RESET = 0x0080  # acts on the rising edge of bit 7


# (mask, value) on the statusword, CiA 402 table 30; checked in this order.
_STATUS_PATTERNS: tuple[tuple[int, int, State], ...] = (
    (0x004F, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State.SWITCHED_ON),
    (0x006F, 0x0027, State.OPERATION_ENABLED),
    (0x006F, 0x0007, State.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State.FAULT),
)

#: Statusword bits of each state (bit 4 "voltage enabled" and 5 "quick stop" as a drive shows them).
STATUS_BITS: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x0000,
    State.SWITCH_ON_DISABLED: 0x0040,
    State.READY_TO_SWITCH_ON: 0x0031,
    State.SWITCHED_ON: 0x0033,
    State.OPERATION_ENABLED: 0x0037,
    State.QUICK_STOP_ACTIVE: 0x0017,
    State.FAULT_REACTION_ACTIVE: 0x001F,
    State.FAULT: 0x0008,
}
STATUS_TARGET_REACHED = 1 << 10
STATUS_WARNING = 1 << 7


def decode_statusword(statusword: int) -> State:
    """The state shown by a statusword (CiA 402 table 30)."""
    for mask, value, state in _STATUS_PATTERNS:
        if statusword & mask == value:
            return state
    raise ValueError(f"statusword 0x{statusword:04X} shows no CiA 402 state")


def decode_controlword(controlword: int) -> Command | None:
    """The device-control command a controlword carries (bits 0–3, 7), or None if none applies.

    Fault reset is reported when bit 7 is set; the caller detects the rising edge.
    """
    if controlword & 0x0080:
        return Command.FAULT_RESET
    if controlword & 0x0002 == 0:
        return Command.DISABLE_VOLTAGE
    if controlword & 0x0006 == 0x0002:
        return Command.QUICK_STOP
    low = controlword & 0x000F
    if low & 0x0007 == 0x0006:
        return Command.SHUTDOWN
    if low == 0x0007:
        return Command.SWITCH_ON
    if low == 0x000F:
        return Command.ENABLE_OPERATION
    return None


def next_state(state: State, command: Command | None) -> State:
    """The state a drive in ``state`` moves to on ``command`` (CiA 402 figure 12).

    Automatic transitions (0, 1, 14: power-up and end of fault reaction) and the
    end of a quick stop are the device's own doing and not covered here.
    """
    if command is None:
        return state
    if state is State.FAULT:
        return State.SWITCH_ON_DISABLED if command is Command.FAULT_RESET else state
    if state in (State.NOT_READY_TO_SWITCH_ON, State.FAULT_REACTION_ACTIVE):
        return state
    if command is Command.DISABLE_VOLTAGE:
        return State.SWITCH_ON_DISABLED
    if state is State.SWITCH_ON_DISABLED:
        return State.READY_TO_SWITCH_ON if command is Command.SHUTDOWN else state
    if state is State.READY_TO_SWITCH_ON:
        return {
            Command.SWITCH_ON: State.SWITCHED_ON,
            Command.ENABLE_OPERATION: State.OPERATION_ENABLED,  # 3 + 4 in one go, as drives allow
            Command.QUICK_STOP: State.SWITCH_ON_DISABLED,
        }.get(command, state)
    if state is State.SWITCHED_ON:
        return {
            Command.ENABLE_OPERATION: State.OPERATION_ENABLED,
            Command.SHUTDOWN: State.READY_TO_SWITCH_ON,
            Command.QUICK_STOP: State.SWITCH_ON_DISABLED,
        }.get(command, state)
    if state is State.OPERATION_ENABLED:
        return {
            Command.DISABLE_OPERATION: State.SWITCHED_ON,
            Command.SHUTDOWN: State.READY_TO_SWITCH_ON,
            Command.QUICK_STOP: State.QUICK_STOP_ACTIVE,
        }.get(command, state)
    if state is State.QUICK_STOP_ACTIVE:
        return State.OPERATION_ENABLED if command is Command.ENABLE_OPERATION else state
    return state


def command_towards(state: State, target: State) -> Command | None:
    """The next command on the way from ``state`` to ``target`` (None when there, or stuck).

    Targets are the stable states a host asks for: SWITCH_ON_DISABLED, READY_TO_SWITCH_ON,
    SWITCHED_ON, OPERATION_ENABLED.
    """
    if state is target:
        return None
    if state is State.FAULT:
        return Command.FAULT_RESET
    if target is State.SWITCH_ON_DISABLED:
        return Command.DISABLE_VOLTAGE
    order = [State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON, State.OPERATION_ENABLED]
    if state is State.QUICK_STOP_ACTIVE:
        return Command.DISABLE_VOLTAGE
    if state not in order or target not in order:
        return None
    i, j = order.index(state), order.index(target)
    if i < j:
        return (Command.SHUTDOWN, Command.SWITCH_ON, Command.ENABLE_OPERATION)[i]
    return (None, Command.DISABLE_VOLTAGE, Command.SHUTDOWN, Command.DISABLE_OPERATION)[i] if j < i else None
