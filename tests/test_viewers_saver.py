"""The savers' shared base (tools/viewers/saver.py): a `.partial` file moved into place once, per-topic
counts."""
import pytest
from tensortouch.tools.viewers.saver import Saver


class _LineSaver(Saver):
    """A minimal saver: one text line per message, a trailer line when the stream ends."""

    def __init__(self, path):
        self._start(path)
        self.fh = open(self.partial, "w") if self.partial else None
        self.ended = 0

    def write(self, topic, text):
        self._count(topic)
        if self.fh:
            self.fh.write(f"{topic} {text}\n")

    def _end(self):
        self.ended += 1
        if self.fh:
            self.fh.write("end\n")
            self.fh.close()


def test_file_grows_as_partial_and_is_moved_into_place_on_close(tmp_path):
    out = tmp_path / "deep" / "rec.txt"
    s = _LineSaver(out)
    assert s.partial == tmp_path / "deep" / "rec.txt.partial" and s.partial.exists() and not out.exists()
    s.write("a/fields", "1")
    s.write("a/fields", "2")
    s.write("a/contacts", "3")
    assert s.counts == {"a/fields": 2, "a/contacts": 1}
    s.close()
    assert out.read_text() == "a/fields 1\na/fields 2\na/contacts 3\nend\n" and not s.partial.exists()
    s.close()                                    # a second close does nothing
    assert s.ended == 1 and out.read_text().endswith("end\n")


def test_without_a_path_only_counts(tmp_path):
    s = _LineSaver(None)
    s.write("b/status", "x")
    s.close()
    assert s.counts == {"b/status": 1} and s.partial is None and s.ended == 1
    assert list(tmp_path.iterdir()) == []


def test_a_subclass_must_say_how_its_stream_ends(tmp_path):
    class Bare(Saver):
        pass

    b = Bare()
    b._start(None)
    with pytest.raises(NotImplementedError):
        b.close()
