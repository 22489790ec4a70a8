"""tools/progress.py: the tools' one progress helper."""
import logging

from tensortouch.tools.progress import count_progress, stage_progress


def test_stage_progress_opens_a_bar_per_stage_and_restores_logging(caplog):
    root = logging.getLogger()
    before = list(root.handlers)
    cb = stage_progress("unit")
    cb("physics", 1, 3)
    assert cb._key == ("physics", 3)
    with caplog.at_level(logging.INFO):
        logging.getLogger("x").info("a log line while a bar is open")
    cb("physics", 3, 3)                 # the last step closes the bar
    assert cb._bar is None and cb._key is None
    cb("render", 1, 2)                  # another stage: a new bar
    assert cb._key == ("render", 2)
    cb.close()
    assert root.handlers == before      # the logging redirect is undone with the bar
    assert "a log line while a bar is open" in caplog.text


def test_count_progress_counts_to_the_end():
    tick = count_progress("network pass", "frame")
    for i in range(1, 6):
        tick(i, 5)
