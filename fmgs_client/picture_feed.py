"""The inspector's picture panel feed: one StreamRender call per (scene, text), newest pose wins.

The 3D view hands every camera change to :meth:`PictureFeed.put` and never waits; a background thread keeps
one pose in flight on a StreamRender call and sends the newest pose each time an answer arrives (poses in
between are dropped here, not queued at the server). A failed stream (the server went away) is reported
and opened again after a pause, with the newest pose, until the feed is closed.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

from fmgs_client.client import FmgsClient, FmgsError
from fmgs_client.types import CameraSpec, RenderResult

RECONNECT_S = 1.0
"""Pause before a failed stream is opened again."""


class PictureFeed:
    """Renders of the newest pose for ``scene`` and ``text`` ("" for colour only), delivered to
    ``on_result(camera, result)`` or ``on_error(error)`` on the feed's thread."""

    def __init__(
        self,
        client: FmgsClient,
        scene: str,
        text: str,
        on_result: Callable[[CameraSpec, RenderResult], None],
        on_error: Callable[[FmgsError], None],
    ) -> None:
        self.client, self.scene, self.text = client, scene, text
        self.outputs = ("relevancy", "rgb", "alpha") if text else ("rgb", "alpha")
        self._on_result, self._on_error = on_result, on_error
        self._cond = threading.Condition()
        self._delivering = threading.RLock()
        """Held while a callback runs: close() waits for it, so nothing is delivered once close() returns
        (a viewer that restarts its feed for a new text would otherwise show the old text's picture).
        Reentrant: a callback may close its own feed."""
        self._newest: CameraSpec | None = None
        self._last: CameraSpec | None = None
        self._in_flight: dict[int, CameraSpec] = {}
        self._closed = False
        self._stream_id = 0
        """Which stream may take poses: a failed stream's request generator can outlive it on a gRPC
        thread, and must not take the poses meant for the next."""
        self._thread = threading.Thread(target=self._run, name=f"picture-{scene}", daemon=True)
        self._thread.start()

    def put(self, camera: CameraSpec) -> None:
        """The view's newest camera (replaces any pose not yet sent)."""
        with self._cond:
            self._newest = camera
            self._cond.notify_all()

    def close(self) -> None:
        """Stop: the open stream ends once its pose is answered; nothing is delivered after this returns
        (it waits for a callback already running)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        with self._delivering:
            pass

    def _deliver(self, callback: Callable, *args) -> None:
        with self._delivering:
            if not self._closed:
                callback(*args)

    def _poses(self, stream_id: int) -> Iterator[CameraSpec]:
        """The request stream: the newest pose whenever nothing is in flight (consumed by gRPC)."""
        seq = 0
        while True:
            with self._cond:
                while self._live(stream_id) and (self._newest is None or self._in_flight):
                    self._cond.wait(0.25)
                if not self._live(stream_id):
                    return
                cam, self._newest = self._newest, None
                self._in_flight[seq] = self._last = cam
            seq += 1
            yield cam

    def _live(self, stream_id: int) -> bool:
        return not self._closed and stream_id == self._stream_id

    def _run(self) -> None:
        while not self._closed:
            with self._cond:
                self._stream_id += 1
                poses = self._poses(self._stream_id)
            try:
                for r in self.client.stream(self.scene, poses, self.text, outputs=self.outputs):
                    with self._cond:
                        cam = self._in_flight.pop(r.sequence, None)
                        self._in_flight.clear()  # an answer settles every older pose
                        self._cond.notify_all()
                    if cam is not None:
                        self._deliver(self._on_result, cam, r)
                error = None  # the server ended the stream (it is shutting down): open another
            except FmgsError as e:
                error = e
            with self._cond:
                self._stream_id += 1  # this stream's request generator stops taking poses
                self._in_flight.clear()
                if self._newest is None:
                    self._newest = self._last  # the view has not moved: render it again
                closed = self._closed
            if closed:
                return
            if error is not None:
                self._deliver(self._on_error, error)
            with self._cond:
                self._cond.wait_for(lambda: self._closed, RECONNECT_S)
