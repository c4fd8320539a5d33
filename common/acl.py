"""The router's access-control policy: each drone reaches only its own keys.

Zenoh matches a connecting session's certificate common name (mTLS) against `subjects`; we give every
drone its id as CN and the edge services the CN `edge`. Default deny, then per drone:

- ingress put on `dynqos/<id>/up/**`: it may publish its own state, camera and status, nothing else;
- ingress declare_subscriber on `dynqos/<id>/down/**` and `dynqos/<id>/ref`: it may listen to its own
  commands, acks, detections and reference (the fallback's `continue` mode reads the reference);
- egress put on those keys: the router delivers them to it;
- egress declare_subscriber on `dynqos/**`: it learns which of its keys the edge listens to (zenoh only
  sends a put where a subscriber was declared, so without this the drone's own state would go nowhere).

Zenoh applies a rule only where the message's key is included in the rule's key expression, so a
drone that declares a wider subscriber (`dynqos/**`) matches no allow rule and is refused.
The edge subject may do anything under `dynqos/**`.
"""

from __future__ import annotations

from typing import Any

from dynqos.common.keys import ROOT, check_uav_id

EDGE_SUBJECT = "edge"


def access_control_policy(drones: tuple[str, ...] | list[str]) -> dict[str, Any]:
    """zenoh's `access_control` config object for `drones` and the edge services."""
    rules: list[dict[str, Any]] = [
        {
            "id": "edge-all",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ["put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
                         "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"],
            "key_exprs": [f"{ROOT}/**"],
        },
        {
            "id": "drone-learns-subscribers",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["declare_subscriber"],
            "key_exprs": [f"{ROOT}/**"],
        },
    ]  # fmt: skip
    subjects: list[dict[str, Any]] = [{"id": EDGE_SUBJECT, "cert_common_names": [EDGE_SUBJECT]}]
    policies: list[dict[str, Any]] = [
        {"id": "edge", "rules": ["edge-all"], "subjects": [EDGE_SUBJECT]},
    ]
    for uav in drones:
        check_uav_id(uav)
        own_down = [f"{ROOT}/{uav}/down/**", f"{ROOT}/{uav}/ref"]
        rules += [
            {
                "id": f"{uav}-publish-up",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put"],
                "key_exprs": [f"{ROOT}/{uav}/up/**"],
            },
            {
                "id": f"{uav}-subscribe-down",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["declare_subscriber"],
                "key_exprs": own_down,
            },
            {
                "id": f"{uav}-receive-down",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put"],
                "key_exprs": own_down,
            },
        ]
        subjects.append({"id": f"drone-{uav}", "cert_common_names": [uav]})
        policies.append(
            {
                "id": f"drone-{uav}",
                "rules": [f"{uav}-publish-up", f"{uav}-subscribe-down", f"{uav}-receive-down",
                          "drone-learns-subscribers"],
                "subjects": [f"drone-{uav}"],
            }
        )  # fmt: skip
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }
