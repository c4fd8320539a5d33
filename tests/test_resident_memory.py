"""The memory the flights record: VmRSS counts a mapped library's pages, RssAnon only what the process
allocated. The soak's leak bound rests on that difference, so it is checked on this machine's kernel."""

from __future__ import annotations

import mmap
import os
from pathlib import Path

import pytest

from dynqos.experiment.processes import resident_memory
from dynqos.reports.summary import memory_figures

MB = 1024  # kB


def test_a_process_that_does_not_exist_has_no_memory() -> None:
    assert resident_memory(2**22 + 12345) is None  # above the kernel's default pid_max


def test_allocated_pages_count_as_anonymous_and_mapped_file_pages_do_not(tmp_path: Path) -> None:
    before = resident_memory(os.getpid())
    assert before is not None
    assert 0 < before.anon_kb <= before.rss_kb

    allocated = bytearray(64 * MB * 1024)
    allocated[:: mmap.PAGESIZE] = b"\x01" * len(allocated[:: mmap.PAGESIZE])  # touch every page
    grown = resident_memory(os.getpid())
    assert grown is not None
    assert grown.anon_kb - before.anon_kb > 56 * MB
    assert grown.rss_kb - before.rss_kb > 56 * MB

    data = tmp_path / "library.bin"
    data.write_bytes(os.urandom(32 * MB * 1024))
    with data.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mapped:
        checksum = sum(mapped[i] for i in range(0, len(mapped), mmap.PAGESIZE))  # fault every page in
        mapped_in = resident_memory(os.getpid())
    assert checksum >= 0
    assert mapped_in is not None
    assert mapped_in.rss_kb - grown.rss_kb > 28 * MB
    assert abs(mapped_in.anon_kb - grown.anon_kb) < 8 * MB
    del allocated


def test_a_flights_memory_figures_come_from_both_columns() -> None:
    samples = [
        (0.0, 100 * MB, 40 * MB),
        (30.0, 120 * MB, 41 * MB),
        (61.0, 130 * MB, 42 * MB),
        (90.0, 125 * MB, 43 * MB),
    ]
    assert memory_figures(samples) == pytest.approx(
        {
            "first": 100.0,
            "after_1min": 130.0,
            "max": 130.0,
            "last": 125.0,
            "anon_first": 40.0,
            "anon_after_1min": 42.0,
            "anon_max": 43.0,
            "anon_last": 43.0,
        }
    )
    assert memory_figures(samples[:2])["anon_after_1min"] is None  # a flight shorter than a minute
