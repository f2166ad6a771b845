"""Where a view goes: an ``.rrd`` file (``rerun FILE.rrd`` opens it) or Rerun's web viewer served
on localhost from the assets inside the rerun-sdk wheel (nothing is downloaded)."""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

import rerun as rr

from sonogym.outputs import OutputPathError

APPLICATION_ID = "sonogym"
WEB_PORT = 9090  # Rerun's defaults
GRPC_PORT = 9876


@dataclass
class Session:
    """An open recording and its sink: ``path`` (an .rrd file) or ``url`` (the web viewer)."""

    rec: rr.RecordingStream
    path: Path | None = None
    url: str | None = None

    def close(self) -> None:
        """Flush everything logged; a file is complete when this returns."""
        self.rec.flush()
        if self.path is not None:
            self.rec.disconnect()


def open_session(
    name: str,
    save: str | Path | None = None,
    web: bool = False,
    web_port: int = WEB_PORT,
    grpc_port: int = GRPC_PORT,
) -> Session:
    """A recording named ``name`` writing to ``save`` or served to the web viewer (one of them).
    Only the ``step`` timeline is recorded (no wall-clock time), so a view is reproducible."""
    if (save is None) == (not web):
        raise ValueError("give a file to save the view to or web=True (one of them)")
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{name}-{uuid.uuid4().hex[:8]}")
    rec.set_log_time_enabled(False)
    rec.send_recording_name(name)
    if save is not None:
        path = Path(save)
        if path.suffix != ".rrd":
            raise ValueError(f"{path}: a Rerun recording is saved as an .rrd file")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(path)
        except (OSError, RuntimeError) as e:  # Rerun raises RuntimeError for a file it cannot make
            raise OutputPathError(
                f"cannot write the view into {path.parent} ({e}); give --save a file in a "
                "folder you can write to"
            ) from None
        return Session(rec, path=path)
    uri = rec.serve_grpc(grpc_port=grpc_port)
    rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=uri)
    return Session(rec, url=f"http://localhost:{web_port}/?url={quote(uri, safe='')}")


def is_sonogym_recording(path: str | Path) -> bool:
    """Whether ``path`` is a Rerun recording that sonogym wrote: an .rrd file (magic ``RRF``)
    whose first message names the application ``sonogym``."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    app = APPLICATION_ID.encode()
    return head.startswith(b"RRF") and bytes([0x0A, len(app)]) + app in head


def serve_until_interrupted(session: Session, log: Callable[[str], None] = print) -> None:
    """Keep the web viewer's servers up (they live in this process) until Ctrl-C."""
    session.rec.flush()
    log(f"web viewer: {session.url} (Ctrl-C to stop)")
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        log("stopped")
