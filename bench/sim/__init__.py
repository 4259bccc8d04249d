"""LIBERO in the simulator (optional `libero` extra; docs/LIBERO_SIM.md).

env.py: LIBERO config, assets, render settings and seeded resets around LeRobot's LiberoEnv;
expert.py: scripted pick-and-place expert (privileged poses); demos.py: demonstrations as a
LeRobotDataset (the "sim" suite source); rollout.py: closed-loop success of any policy.
Importing this package does not import LIBERO; `env.configure()` does, on first use.
"""
