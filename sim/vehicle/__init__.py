"""The vehicle stand-in: quadrotor dynamics, a PX4-like flight controller that speaks MAVLink, the
world it flies in, and the RGB-D renderer behind the simulated camera."""

MAX_INSTANCE = 254  # vehicle N of a fleet has MAVLink system id N+1, and system ids are 1..255
