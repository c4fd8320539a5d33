"""The Foxglove layout shipped in docs/foxglove-layout.json: one drone's view as `dynqos view` and
`dynqos record` publish it (dynqos/observers/telemetry.py), built with the SDK's layout types so that it
stays a valid layout. `python -m dynqos.observers.layout > docs/foxglove-layout.json` writes it again; a
test keeps the file and the topics it reads in step with the code."""

from __future__ import annotations

import json
import sys

from foxglove import layouts as fl

from dynqos.observers.telemetry import WORLD


def layout(uav: str = "uav1") -> fl.Layout:
    d = f"/{uav}"
    scene = fl.ThreeDeePanel(
        title=f"{uav}: pose, reference, risk zone, world",
        config=fl.ThreeDeeConfig(
            follow_tf=WORLD,
            topics={
                "/world": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
                f"{d}/scene": fl.BaseRendererSceneUpdateTopicSettings(visible=True),
                f"{d}/pose": fl.BaseRendererPoseTopicSettings(visible=True, type="arrow"),
            },
        ),
    )
    camera = fl.ImagePanel(
        title=f"{uav}: camera and detections",
        config=fl.ImageConfig(
            image_mode=fl.ImageModeConfig(
                image_topic=f"{d}/camera/rgb",
                annotations={f"{d}/camera/annotations": fl.ImageAnnotationSettings(visible=True)},
            )
        ),
    )
    latency = fl.PlotPanel(
        title="C&C RTT and camera latency (ms)",
        config=fl.PlotConfig(
            paths=[
                fl.PlotSeries(value=f"{d}/status.rtt_ms", label="C&C RTT"),
                fl.PlotSeries(value=f"{d}/status.camera_latency_ms", label="camera latency"),
            ],
            show_legend=True,
        ),
    )
    probabilities = fl.PlotPanel(
        title="P_lat and the camera rate",
        config=fl.PlotConfig(
            paths=[
                fl.PlotSeries(value=f"{d}/status.p_lat", label="P_lat"),
                fl.PlotSeries(value=f"{d}/status.camera_rate_factor", label="camera rate factor"),
            ],
            show_legend=True,
        ),
    )
    states = fl.StateTransitionsPanel(
        title="supervisor",
        config=fl.StateTransitionsConfig(
            paths=[
                fl.StateTransitionsSeries(value=f"{d}/status.state", label="state"),
                fl.StateTransitionsSeries(value=f"{d}/status.flow", label="flow"),
                fl.StateTransitionsSeries(value=f"{d}/status.control_source", label="control"),
                fl.StateTransitionsSeries(value=f"{d}/status.risk", label="risk"),
                fl.StateTransitionsSeries(value=f"{d}/status.qos_grant", label="grant"),
            ]
        ),
    )
    logs = fl.LogPanel(title="transitions and QoS decisions", config=fl.LogConfig(topic_to_render="/log"))
    status = fl.RawMessagesPanel(title="status", config=fl.RawMessagesConfig(topic_path=f"{d}/status"))
    left = fl.SplitContainer(
        direction="column",
        items=[fl.SplitItem(proportion=2, content=scene), fl.SplitItem(content=camera)],
    )
    right = fl.SplitContainer(
        direction="column",
        items=[
            fl.SplitItem(content=latency),
            fl.SplitItem(content=probabilities),
            fl.SplitItem(content=states),
            fl.SplitItem(content=logs),
            fl.SplitItem(content=status),
        ],
    )
    return fl.Layout(
        content=fl.SplitContainer(items=[fl.SplitItem(content=left), fl.SplitItem(content=right)])
    )


def layout_json(uav: str = "uav1") -> str:
    return json.dumps(json.loads(layout(uav).to_json()), indent=1) + "\n"


if __name__ == "__main__":  # pragma: no cover
    sys.stdout.write(layout_json())
