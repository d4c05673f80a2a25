//! Closed-loop rollouts of a SmolVLA policy in the SO-100 simulation (being written).
