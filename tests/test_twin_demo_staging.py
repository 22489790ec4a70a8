"""`tensortouch twin demo` records the new demo under the cache, not beside the shipped one: a stopped run
leaves nothing in the source tree (the documented-commands check stops long commands)."""
from pathlib import Path


def test_demo_staging_is_under_the_cache_not_beside_the_demo(tmp_path, monkeypatch):
    from tensortouch.contracts import paths
    from tensortouch.tools.twin.demo import staging_dir

    monkeypatch.setenv("TENSORTOUCH_CACHE", str(tmp_path / "c"))
    out = paths.demo_dir()
    st = staging_dir(out)
    assert st.is_relative_to(tmp_path / "c") and st.name == out.name
    assert not st.is_relative_to(Path(out).parent)
