"""The direct CDR JointState reader (:func:`protocol.ros2.read_joint_state`) against the decoder ``mcap_ros2``
builds from the definition: the same message for any JointState, and a ValueError (never another error, never a
message) for a payload cut anywhere."""
from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.ros2 import JOINT_STATE, decoder, encode_joint_state, read_joint_state, same_joint_state

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@st.composite
def joint_states(draw):
    n = draw(st.integers(0, 12))
    names = draw(st.lists(st.text(min_size=0, max_size=12).filter(lambda s: "\x00" not in s), min_size=n,
                          max_size=n))
    pos = draw(st.lists(finite, min_size=n, max_size=n))
    vel = draw(st.one_of(st.just([]), st.lists(finite, min_size=n, max_size=n)))
    eff = draw(st.one_of(st.just([]), st.lists(finite, min_size=n, max_size=n)))
    frame = draw(st.text(max_size=9).filter(lambda s: "\x00" not in s))
    stamp_ns = draw(st.integers(0, 2**31 * 10**9 - 1))
    return encode_joint_state(0.0, names, pos, vel, eff, frame_id=frame, stamp_ns=stamp_ns)


@settings(max_examples=300, deadline=None)
@given(joint_states())
def test_reads_what_the_definitions_decoder_reads(payload):
    assert same_joint_state(read_joint_state(payload), decoder(JOINT_STATE)(payload))


@settings(max_examples=100, deadline=None)
@given(joint_states(), st.data())
def test_a_payload_cut_short_is_a_value_error(payload, data):
    cut = data.draw(st.integers(0, len(payload) - 1))
    with pytest.raises(ValueError):
        read_joint_state(payload[:cut])


def test_big_endian_is_refused():
    payload = encode_joint_state(1.0, ["a"], [1.0], [], [])
    with pytest.raises(ValueError):
        read_joint_state(b"\x00\x00" + payload[2:])
