"""First-party mocapflow stages: thin nodes over mocapflow.mocap."""
