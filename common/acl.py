"""The router's access-control policy: every identity reaches only the keys its job needs.

Zenoh matches a connecting session's certificate common name (mTLS) against `subjects`. A drone's CN
is its id; each edge service has its own CN (`edge-mpc`, `edge-planner`, `edge-fleet-planner`,
`edge-detector`, `edge-qos`, `edge-ros2`), so a compromised detector, which parses camera frames from
the network, cannot command a drone.
Default deny, then:

- a drone publishes only `dynqos/<id>/up/**` and receives only `dynqos/<id>/down/**` and
  `dynqos/<id>/ref` (the fallback's `continue` mode reads the reference); it both publishes and
  receives `dynqos/<id>/clock`, the preflight's clock probes that the router stamps; it holds its
  presence token `dynqos/<id>/alive`, which the MPC and planner watch (and may not declare);
- an edge service publishes only its outputs and subscribes only to its inputs (`EDGE_ROLES`);
- everyone may learn which keys are subscribed (egress declare_subscriber on `dynqos/**`): zenoh only
  sends a put where a subscriber was declared, so without this no publisher's data would go anywhere.

A rule applies only where the message's key is included in the rule's key expression, so a session
that declares a wider subscriber (`dynqos/**`, `**`) matches no allow rule and is refused. Liveliness
is allowed only where replicas of one edge service find each other (`dynqos/edge/replicas/<service>/**`,
for that service's identity alone) and where a drone announces itself (`dynqos/<id>/alive`, declared by
that drone alone, watched by the MPC and the planner); queries and queryables are used by no dynqos
component and are denied to everyone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dynqos.common.keys import (
    ROOT,
    Downlink,
    Stream,
    any_replica_beat,
    any_replica_of,
    any_state_watch,
    check_task_name,
    check_uav_id,
    clock_probe,
    downlink_all_drones,
    drone_presence,
    drones_present,
    task_uplink_all_drones,
    uplink_all_drones,
)


@dataclass(frozen=True, slots=True)
class EdgeRole:
    """What one edge service may read (subscribe to) and write (publish), and the liveliness tokens its
    replicas declare and watch."""

    reads: tuple[str, ...]
    writes: tuple[str, ...]
    tokens: tuple[str, ...] = ()
    watches: tuple[str, ...] = ()  # liveliness tokens it may watch and query, never declare


EDGE_ROLES: dict[str, EdgeRole] = {
    "mpc": EdgeRole(
        # the replicas' heartbeats too: a standby watches the beats of the one flying a drone
        # (edge/replicas.py, `beats`), and, with standby_reads = "copies", the states it copies for it
        reads=(
            uplink_all_drones(Stream.STATE),
            downlink_all_drones(Downlink.REFERENCE),
            any_replica_beat("mpc"),
            any_state_watch("mpc"),
        ),
        writes=(downlink_all_drones(Downlink.COMMAND), any_replica_beat("mpc"), any_state_watch("mpc")),
        tokens=(any_replica_of("mpc"),),
        watches=(drones_present(),),  # it follows the drones it serves (edge/feeds.py)
    ),
    "planner": EdgeRole(
        # the references too: a standby planner follows the mission time of the one it stands by for;
        # and the missions the ROS 2 bridge sends
        reads=(
            uplink_all_drones(Stream.STATE),
            downlink_all_drones(Downlink.REFERENCE),
            downlink_all_drones(Downlink.MISSION),
        ),
        writes=(downlink_all_drones(Downlink.REFERENCE),),
        tokens=(any_replica_of("planner"),),
        watches=(drones_present(),),
    ),
    # where each drone starts from its states; it sends the missions of the fleet's plan to the planners
    "fleet-planner": EdgeRole(
        reads=(uplink_all_drones(Stream.STATE),),
        writes=(downlink_all_drones(Downlink.MISSION),),
    ),
    "detector": EdgeRole(
        reads=(uplink_all_drones(Stream.CAMERA_RGB), uplink_all_drones(Stream.CAMERA_DEPTH)),
        writes=(downlink_all_drones(Downlink.CAMERA_ACK), downlink_all_drones(Downlink.DETECTIONS)),
        tokens=(any_replica_of("detector"),),  # detectors share the drones (edge/membership.py, LiveSet)
    ),
    # ROS 2 topics too (rmw_zenoh's keys and tokens, under the domain and prefix the router's config
    # names: ros2_topics); on dynqos keys it writes only the missions ROS 2 nodes ask for
    "ros2": EdgeRole(
        reads=(
            uplink_all_drones(Stream.STATE),
            uplink_all_drones(Stream.STATUS),
            uplink_all_drones(Stream.CAMERA_RGB),
            downlink_all_drones(Downlink.DETECTIONS),
            downlink_all_drones(Downlink.QOS_GRANT),
            downlink_all_drones(Downlink.QOS_DECISION),
        ),
        writes=(downlink_all_drones(Downlink.MISSION),),
    ),
    "qos": EdgeRole(
        reads=(uplink_all_drones(Stream.QOS),),
        writes=(
            downlink_all_drones(Downlink.QOS_GRANT),
            downlink_all_drones(Downlink.QOS_DECISION),
            downlink_all_drones(Downlink.QOS_MONITORING),  # the core's delay reports (NEF backend)
        ),
        tokens=(any_replica_of("qos"),),  # one agent active, the others standing by (edge/qos/leadership.py)
    ),
}
EDGE_PREFIX = "edge-"
ROUTER_COMMON_NAME = "router"
TASK_PREFIX = "task-"  # a user's offloaded task's service: task-<name>, its identity edge-task-<name>


def task_role(task: str) -> EdgeRole:
    """A user's task service (docs/offload.md): it reads every drone's requests of that task, writes only
    its answers, and its replicas find each other by their tokens."""
    service = TASK_PREFIX + check_task_name(task)
    return EdgeRole(
        reads=(task_uplink_all_drones(task),),
        writes=(f"{ROOT}/*/down/task/{task}",),
        tokens=(any_replica_of(service),),
    )


def task_common_name(task: str) -> str:
    """The certificate CN of a user's task service (`edge-task-look-at`)."""
    return EDGE_PREFIX + TASK_PREFIX + check_task_name(task)


def edge_common_name(service: str) -> str:
    """The certificate CN of an edge service (`edge-mpc`)."""
    if service not in EDGE_ROLES:
        raise ValueError(f"no edge service {service!r} (known: {', '.join(EDGE_ROLES)})")
    return EDGE_PREFIX + service


def reserved_name(name: str) -> bool:
    """Names that are identities of the edge, never a drone's id."""
    return name in (ROUTER_COMMON_NAME, "edge") or name.startswith(EDGE_PREFIX)


def _rule(rule_id: str, flow: str, messages: list[str], keys: list[str] | tuple[str, ...]) -> dict[str, Any]:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": list(keys),
    }


def _reader_and_writer(
    name: str,
    reads: list[str] | tuple[str, ...],
    writes: list[str] | tuple[str, ...],
    tokens: tuple[str, ...] = (),
    watches: tuple[str, ...] = (),
) -> list[dict[str, Any]]:
    """Rules for a subject that subscribes to `reads`, publishes on `writes` and, where it has
    `tokens`, declares, queries and watches liveliness tokens there (`watches`: only the last two)."""
    rules = [
        _rule(f"{name}-subscribe", "ingress", ["declare_subscriber"], reads),
        _rule(f"{name}-receive", "egress", ["put"], reads),
    ]
    if writes:
        rules.append(_rule(f"{name}-publish", "ingress", ["put"], writes))
    if tokens:
        rules += [
            _rule(
                f"{name}-tokens",
                "ingress",
                ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
                tokens,
            ),
            _rule(f"{name}-tokens-seen", "egress", ["liveliness_token", "reply"], tokens),
        ]
    if watches:
        rules += [
            _rule(f"{name}-watch", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], watches),
            _rule(f"{name}-watched-seen", "egress", ["liveliness_token", "reply"], watches),
        ]
    return rules


def ros2_topics(domain_id: int, prefix: str) -> tuple[str, ...]:
    """The rmw_zenoh data keys of what `dynqos edge ros2` publishes: `/<prefix>/...` and `/tf`."""
    return (f"{domain_id}/{prefix}/**", f"{domain_id}/tf/**")


def ros2_steering(domain_id: int, prefix: str) -> tuple[str, ...]:
    """The rmw_zenoh data keys on which ROS 2 nodes steer a drone: its `mission` (a nav_msgs/Path) and
    `goal` (a geometry_msgs/PoseStamped), any type hash; not `mission/status`, which is the bridge's.
    (The DDS type names as edge/ros2/wire.py spells them; tests/test_ros2_steer.py checks they agree.)"""
    return (
        f"{domain_id}/{prefix}/*/mission/nav_msgs::msg::dds_::Path_/*",
        f"{domain_id}/{prefix}/*/goal/geometry_msgs::msg::dds_::PoseStamped_/*",
    )


def ros2_tokens(domain_id: int) -> tuple[str, ...]:
    """rmw_zenoh's liveliness tokens of one domain (nodes, publishers, subscribers)."""
    return (f"@ros2_lv/{domain_id}/**",)


def access_control_policy(
    drones: tuple[str, ...] | list[str],
    ros2_clients: tuple[str, ...] | list[str] = (),
    ros2_domain_id: int = 0,
    ros2_prefix: str = "dynqos",
    tasks: tuple[str, ...] | list[str] = (),
) -> dict[str, Any]:
    """zenoh's `access_control` config object for `drones`, the edge services and the ROS 2 nodes named
    by `ros2_clients` (the bridge's topics and the domain's discovery tokens; they write only a drone's
    mission or goal)."""
    rules: list[dict[str, Any]] = [
        _rule("learn-subscribers", "egress", ["declare_subscriber"], [f"{ROOT}/**"]),
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []

    def grant(subject: str, common_name: str, own_rules: list[dict[str, Any]]) -> None:
        rules.extend(own_rules)
        subjects.append({"id": subject, "cert_common_names": [common_name]})
        policies.append(
            {
                "id": subject,
                "rules": [r["id"] for r in own_rules] + ["learn-subscribers"],
                "subjects": [subject],
            }
        )

    topics, tokens = ros2_topics(ros2_domain_id, ros2_prefix), ros2_tokens(ros2_domain_id)
    steering = ros2_steering(ros2_domain_id, ros2_prefix)
    for service, role in EDGE_ROLES.items():
        cn = edge_common_name(service)
        if service == "ros2":  # its topics lie outside dynqos/**: it learns their subscribers by a rule
            own = _reader_and_writer(cn, (*role.reads, *steering), (*topics, *role.writes), tokens)
            grant(cn, cn, [*own, _rule(f"{cn}-learn-subscribers", "egress", ["declare_subscriber"], topics)])
            continue
        grant(cn, cn, _reader_and_writer(cn, role.reads, role.writes, role.tokens, role.watches))
    for task in tasks:  # the user's own services, each only its task's keys
        cn, role = task_common_name(task), task_role(task)
        grant(cn, cn, _reader_and_writer(cn, role.reads, role.writes, role.tokens))
    for name in ros2_clients:
        if reserved_name(name) or name in drones:
            raise ValueError(f"{name!r} is an edge or drone identity, not a ROS 2 client")
        # it reads the bridge's topics and writes only a drone's mission or goal (which the bridge checks)
        own = _reader_and_writer(name, topics, steering, tokens)
        grant(
            f"ros2-{name}",
            name,
            [*own, _rule(f"{name}-learn-steering", "egress", ["declare_subscriber"], steering)],
        )
    for uav in drones:
        check_uav_id(uav)
        if reserved_name(uav):
            raise ValueError(f"{uav!r} is an edge identity, not a drone id")
        own_down = [f"{ROOT}/{uav}/down/**", f"{ROOT}/{uav}/ref", clock_probe(uav)]
        own_up = [f"{ROOT}/{uav}/up/**", clock_probe(uav)]
        grant(f"drone-{uav}", uav, _reader_and_writer(uav, own_down, own_up, (drone_presence(uav),)))
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
