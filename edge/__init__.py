"""The offloaded half of the loop: zenoh router, MPC, mission planner, circle detector."""
