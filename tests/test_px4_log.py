"""What PX4 did, read from its ULog's vehicle_status (dynqos/reports/px4_log.py): its modes, its
failsafes and whether it flew the whole recorded flight in OFFBOARD, on made-up samples."""

from __future__ import annotations

from dynqos.experiment.vehicles import contacts
from dynqos.reports.px4_log import CLOCK_SHARE, failsafe_onsets, flight_figures, mode_name, mode_spans
from dynqos.sim.vehicle.world import default_world

S = 1_000_000  # microseconds, PX4's clock


def test_the_modes_of_a_flight_in_order_with_how_long_each_lasted() -> None:
    times = [0, 1 * S, 4 * S, 5 * S, 9 * S, 12 * S, 40 * S]
    states = [4, 4, 17, 17, 4, 14, 4]  # loiter, take-off, loiter, offboard, loiter (the daemon's exit)
    spans = mode_spans(times, states, end_us=41 * S)
    assert [(s.mode, s.start_s, s.duration_s) for s in spans] == [
        ("AUTO_LOITER", 0.0, 4.0),
        ("AUTO_TAKEOFF", 4.0, 5.0),
        ("AUTO_LOITER", 9.0, 3.0),
        ("OFFBOARD", 12.0, 28.0),
        ("AUTO_LOITER", 40.0, 1.0),
    ]
    figures = flight_figures(spans, [], flight_s=28.0)
    assert (figures["offboard_s"], figures["offboard_entries"], figures["offboard_whole_flight"]) == (
        28.0,
        1,
        True,
    )


def test_a_mode_shown_while_disarmed_is_no_flight_in_it() -> None:
    """Landed and disarmed, PX4 shows the mode last chosen (OFFBOARD) again: not a second entry."""
    times = [0, 2 * S, 10 * S, 38 * S, 45 * S]
    states = [4, 14, 14, 18, 14]
    armed = [False, True, True, True, False]
    spans = mode_spans(times, states, end_us=46 * S, armed=armed)
    assert [s.mode for s in spans] == [
        "AUTO_LOITER (disarmed)",
        "OFFBOARD",
        "AUTO_LAND",
        "OFFBOARD (disarmed)",
    ]
    assert flight_figures(spans, [], flight_s=30.0)["offboard_whole_flight"] is True


def test_leaving_offboard_mid_flight_or_a_short_stretch_is_not_the_whole_flight() -> None:
    left = mode_spans([0, 10 * S, 20 * S, 21 * S], [14, 18, 14, 4], end_us=40 * S)
    assert flight_figures(left, [], flight_s=10.0)["offboard_whole_flight"] is False  # entered twice
    short = mode_spans([0, 10 * S], [14, 4], end_us=11 * S)
    assert flight_figures(short, [], flight_s=10.0 / CLOCK_SHARE + 0.1)["offboard_whole_flight"] is False
    # PX4's lockstep clock runs a little slower than the wall's: 29.7 s of PX4's time is a 30 s flight
    slow = mode_spans([0, int(29.7 * S)], [14, 4], end_us=30 * S)
    assert flight_figures(slow, [], flight_s=30.0)["offboard_whole_flight"] is True


def test_each_failsafe_is_counted_once_when_it_rises_with_the_mode_it_sent_px4_to() -> None:
    times = [0, 1 * S, 2 * S, 3 * S, 4 * S, 5 * S]
    flags = [0, 1, 1, 0, 1, 0]
    states = [14, 18, 18, 18, 4, 4]
    assert failsafe_onsets(times, flags, states) == [
        {"t_s": 1.0, "mode": "AUTO_LAND"},
        {"t_s": 4.0, "mode": "AUTO_LOITER"},
    ]


def test_modes_px4_may_add_have_a_name_that_says_what_they_are() -> None:
    assert mode_name(14) == "OFFBOARD"
    assert mode_name(23) == "EXTERNAL1"
    assert mode_name(99) == "nav_state 99"


def test_contacts_with_the_world_are_found_along_px4s_track() -> None:
    """PX4's world has no obstacles: what the drone touched is read from its track in dynqos's world,
    with the rule dynqos's vehicle applies in flight; one entry per contact, none on the ground."""
    world = default_world()
    pillar = world.cylinders[0]
    at_pillar = (pillar.center_m[0], pillar.center_m[1] - pillar.radius_m, -1.0)
    track = [
        (0.0, (pillar.center_m[0], pillar.center_m[1], 0.0)),  # standing on the floor under it: no contact
        (1.0, (0.0, 0.0, -1.5)),
        (2.0, at_pillar),
        (2.1, at_pillar),  # still touching: the same contact
        (3.0, (0.0, 0.0, -1.5)),
        (4.0, at_pillar),
    ]
    found = contacts(world, track)
    assert [(c["t_s"], c["with"]) for c in found] == [(2.0, "cylinder 0"), (4.0, "cylinder 0")]
