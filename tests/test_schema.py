"""The variable schema shared by features, causal learning and the gate."""

import numpy as np
import pytest
import torch

from torchrl_causal.schema import (
    ACTION_NAMES,
    DEFAULT_SCHEMA,
    REWARD_NODE,
    Variable,
    VariableSchema,
)


def test_default_schema_matches_thesis():
    assert DEFAULT_SCHEMA.names == (
        "depth_center",
        "depth_top_left",
        "depth_top_right",
        "depth_bottom_left",
        "depth_bottom_right",
        "goal_in_sight",
        "goal_distance",
        "goal_angle",
        "altitude",
    )
    assert DEFAULT_SCHEMA.cardinalities == (2, 2, 2, 2, 2, 2, 3, 3, 3)
    assert DEFAULT_SCHEMA.n_states == 1728
    assert len(ACTION_NAMES) == 8 and ACTION_NAMES[0] == "forward"


def test_state_index_is_a_bijection_in_all_states_order():
    states = DEFAULT_SCHEMA.all_states()
    assert states.shape == (1728, 9)
    idx = DEFAULT_SCHEMA.state_index(torch.from_numpy(states))
    assert torch.equal(idx, torch.arange(1728))
    # numpy ravel_multi_index agrees (C order)
    ref = np.ravel_multi_index(states.T, DEFAULT_SCHEMA.cardinalities)
    assert np.array_equal(idx.numpy(), ref)


def test_node_names_and_cardinalities():
    nodes = DEFAULT_SCHEMA.node_names()
    assert len(nodes) == 19 and nodes[-1] == REWARD_NODE
    cards = DEFAULT_SCHEMA.node_cardinalities()
    assert cards["goal_angle_t"] == 3 and cards["goal_angle_t1"] == 3 and cards["reward"] == 2
    labels = DEFAULT_SCHEMA.node_labels()
    assert labels["altitude_t1"] == ["close_ground", "good", "far_ground"]


def test_bad_schema_input_is_rejected():
    with pytest.raises(ValueError, match="identifier"):
        Variable("not a name", ("a", "b"))
    with pytest.raises(ValueError, match="at least 2"):
        Variable("x", ("a",))
    with pytest.raises(ValueError, match="Duplicate"):
        VariableSchema((Variable("x", ("a", "b")), Variable("x", ("a", "b"))))
    with pytest.raises(KeyError, match="nope"):
        DEFAULT_SCHEMA.index("nope")
    with pytest.raises(ValueError, match="last dim 9"):
        DEFAULT_SCHEMA.state_index(torch.zeros(3, 4, dtype=torch.long))
