"""candidates.py recomputes exactly the stale candidates: all of them when the folder's record
predates the library's output rule (OUTPUT), none when it is current."""
import json
import os
import stat

from gdrecon_py import candidates as cd


def fake_gdrecon(tmp_path):
    """A stand-in CLI that writes its -o file and logs the call."""
    log = tmp_path / "calls.log"
    exe = tmp_path / "gdrecon"
    exe.write_text("#!/bin/sh\n"
                   f"echo \"$@\" >> {log}\n"
                   "while [ $# -gt 0 ]; do [ \"$1\" = -o ] && : > \"$2\"; shift; done\n")
    exe.chmod(exe.stat().st_mode | stat.S_IEXEC)
    return str(exe), log


def calls(log):
    return log.read_text().splitlines() if log.exists() else []


def test_a_record_from_before_the_output_rule_recomputes_every_candidate(tmp_path):
    exe, log = fake_gdrecon(tmp_path)
    folder = tmp_path / "set"
    (folder / "candidates").mkdir(parents=True)
    (folder / "a_4spp.exr").write_bytes(b"")
    # Every candidate present, recorded with today's options but without the output rule.
    for name in cd.CANDIDATES:
        open(cd.path(str(folder), "a_4spp", name), "w").close()
    with open(folder / "candidates" / "options.json", "w") as f:
        json.dump(cd.CANDIDATES, f)
    cd.main([str(folder), "--gdrecon", exe])
    assert len(calls(log)) == len(cd.CANDIDATES)
    with open(folder / "candidates" / "options.json") as f:
        assert json.load(f)["output"] == cd.OUTPUT
    # Now current: nothing to do.
    os.remove(log)
    cd.main([str(folder), "--gdrecon", exe])
    assert calls(log) == []
