"""Small files written so that a reader never sees half of one: a temporary file beside it, then a rename."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path


def write_text_atomically(path: Path, text: str) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, prefix=f".{path.name}.", suffix=".tmp", delete=False) as tmp:
        tmp.write(text)
    os.replace(tmp.name, path)


def write_json_atomically(path: Path, payload) -> None:
    write_text_atomically(path, json.dumps(payload, indent=2))
