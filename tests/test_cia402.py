"""CiA 402 vocabulary: statusword decoding, controlword commands, the state graph."""

import pytest

from commission.drive.cia402 import (
    STATUS_BITS, Command, State, command_towards, decode_controlword, decode_statusword, next_state,
)


@pytest.mark.parametrize("state", list(State))
def test_status_bits_decode_to_their_state(state):
    assert decode_statusword(STATUS_BITS[state]) is state
    # manufacturer bits and "target reached" do not change the state
    assert decode_statusword(STATUS_BITS[state] | 0xC400) is state


def test_commands_decode():
    assert decode_controlword(0x06) is Command.SHUTDOWN
    assert decode_controlword(0x07) is Command.SWITCH_ON
    assert decode_controlword(0x0F) is Command.ENABLE_OPERATION
    assert decode_controlword(0x00) is Command.DISABLE_VOLTAGE
    assert decode_controlword(0x02) is Command.QUICK_STOP
    assert decode_controlword(0x0B) is Command.QUICK_STOP
    assert decode_controlword(0x80) is Command.FAULT_RESET


def test_path_to_operation_enabled_and_back():
    state = State.SWITCH_ON_DISABLED
    seen = []
    while (cmd := command_towards(state, State.OPERATION_ENABLED)) is not None:
        seen.append(cmd)
        state = next_state(state, cmd)
    assert state is State.OPERATION_ENABLED
    assert seen == [Command.SHUTDOWN, Command.SWITCH_ON, Command.ENABLE_OPERATION]
    while (cmd := command_towards(state, State.SWITCH_ON_DISABLED)) is not None:
        state = next_state(state, cmd)
    assert state is State.SWITCH_ON_DISABLED


def test_fault_needs_reset_and_quick_stop_only_from_enabled():
    assert next_state(State.FAULT, Command.ENABLE_OPERATION) is State.FAULT
    assert next_state(State.FAULT, Command.FAULT_RESET) is State.SWITCH_ON_DISABLED
    assert next_state(State.OPERATION_ENABLED, Command.QUICK_STOP) is State.QUICK_STOP_ACTIVE
    assert next_state(State.SWITCHED_ON, Command.QUICK_STOP) is State.SWITCH_ON_DISABLED
