"""What every benchmark shares: when and where it ran, and how its result is written."""

from __future__ import annotations

import json
import os
import platform
from datetime import datetime, timezone
from pathlib import Path
from typing import Any


def provenance() -> dict[str, Any]:
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, python {platform.python_version()}",
    }


def emit(result: dict[str, Any], table: str, out: Path | None) -> int:
    """Print the JSON result and its Markdown table; also write the JSON to `out` if given."""
    text = json.dumps(result, indent=2)
    if out is not None:
        out.write_text(text + "\n")
    print(text)
    print(table)
    return 0
