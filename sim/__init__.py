"""Stand-ins for what cannot run here: a quadrotor that speaks MAVLink, a camera, a 5G cell."""
