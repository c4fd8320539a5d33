"""The vehicle stand-in: quadrotor dynamics, a PX4-like flight controller that speaks MAVLink, the
world it flies in, and the RGB-D renderer behind the simulated camera."""
