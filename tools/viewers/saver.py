"""What the savers share: a file written as `<name>.partial` and moved into place (fsynced) when the
saver closes, a count of messages per topic, and a close that runs once."""
from __future__ import annotations

from pathlib import Path

from ...contracts.files import finish_partial, partial_path


class Saver:
    """Base of the `tensortouch.savers`: subclasses call `_start(path)` and `_count(topic)`, and put what
    ends their stream in `_end()`."""

    path: Path | None = None
    partial: Path | None = None

    def _start(self, path: str | Path | None) -> None:
        """Counts start at zero; with a path, the partial file next to it is where the stream writes."""
        self.counts: dict[str, int] = {}
        self._closed = False
        if path is not None:
            self.path = Path(path)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.partial = partial_path(self.path)

    def _count(self, topic: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1

    def _end(self) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """End the stream; for a file, finish it and move it into place (fsynced). A second close does nothing."""
        if self._closed:
            return
        self._closed = True
        self._end()
        if self.partial is not None:
            finish_partial(self.partial, self.path)
