"""The MPC: the quadratic program (pure), the per-drone controller that solves it, and the service
that feeds it states and references and publishes commands."""
