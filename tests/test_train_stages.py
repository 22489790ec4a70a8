"""Build stages (tools/train/stages.py): a fine-tuned package names the checkpoint it started from."""
import json


def test_a_fine_tuned_package_names_its_init_checkpoint(tmp_path):
    import hashlib

    from tensortouch.tools.train.stages import _record_init

    run = tmp_path / "runs" / "fit-x"
    run.mkdir(parents=True)
    (run / "best.pt").write_bytes(b"weights")
    (run / "config.json").write_text(json.dumps({"epochs": 30}))
    (tmp_path / "manifest.json").write_text(json.dumps({"training": {"command": "c"}}))
    _record_init(tmp_path, run / "best.pt")
    init = json.loads((tmp_path / "manifest.json").read_text())["training"]["init_from"]
    assert init["sha256"] == hashlib.sha256(b"weights").hexdigest() and init["fit_config"] == {"epochs": 30}
