"""Stable-Baselines3 PPO on ParcelPick-v0's pixel action mode (a learning-from-reward baseline)."""
