"""A task of your own, offloaded with dynqos: face a point of interest while the MPC flies the mission.

The edge computes the heading from the drone's position to the point (a stand-in for your own work: a
neural detector, a SLAM back end). Onboard, the drone asks 10 times a second, turns to each answer that
comes within 80 ms, and when answers are late or absent it holds the heading it had (the fallback).

    dynqos edge serve examples/look_at.py:EDGE                 # at the edge
    dynqos onboard --set 'onboard.tasks=["examples/look_at.py:ONBOARD"]'  # on the drone
"""

import math

import msgspec

from dynqos.offload import Drone, Edge, Onboard, Steer, Task

POINT_M = (0.0, 0.0, -1.5)  # local NED: what the camera should face


class Where(msgspec.Struct):
    pos_m: tuple[float, float, float]


class Heading(msgspec.Struct):
    yaw_rad: float


TASK = Task("look-at", request=Where, answer=Heading, rate_hz=10, deadline_s=0.08, flow="control")


def look(where: Where) -> Heading:
    """At the edge: the heading from the drone to the point."""
    north, east = POINT_M[0] - where.pos_m[0], POINT_M[1] - where.pos_m[1]
    return Heading(math.atan2(east, north))


def ask(drone: Drone) -> Where | None:
    return Where(drone.pos_m) if drone.flying else None


def turn(heading: Heading, drone: Drone) -> Steer:
    return Steer(yaw_rad=heading.yaw_rad)


def hold(drone: Drone) -> Steer:
    """No answer in time: keep the heading the drone has now."""
    return Steer(yaw_rad=drone.yaw_rad)


EDGE = Edge(TASK, handle=look)
ONBOARD = Onboard(TASK, request=ask, apply=turn, fallback=hold)
