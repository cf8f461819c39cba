"""Learned end-to-end policies beside the paper's architecture (SPEC §6; docs/learned.md): imitation of the hybrid
controller from camera frames (behaviour cloning + DAgger), the learned hybrid policy, PPO, and their evaluation."""
