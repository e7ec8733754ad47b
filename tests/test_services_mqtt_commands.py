"""MQTT fault commands and axis names as a user sends them: `virtualaxis serve --mqtt` against a real mosquitto
broker and a paho client (a repeated JSON key, magnitudes beyond the i32 of 0x5FF4), and `serve` refusing axis
names at start (a topic wildcard or separator with --mqtt, a control character always) with one `error:` line
naming where the name comes from, exit 2."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import pytest
from served_drive import CLI, ROOT, served
from services_fixtures import mosquitto  # noqa: F401 (fixture)
from test_fault_injection_services import Commands, _side_line

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile
ROOT_PATH = Path(ROOT)


def test_repeated_keys_and_magnitudes_beyond_i32_are_refused_and_nothing_is_injected(mosquitto):  # noqa: F811
    cmd = Commands(mosquitto.port).at("cell5", "X")
    with served("--axis", "X=1:configs/seed000-hust.toml", "--mqtt", mosquitto.url, "--machine", "cell5",
                "--allow-fault-injection") as srv:
        _side_line(srv, "mqtt:")
        sub = cmd.sub
        sub.wait(lambda: any(s["status"] == "online" for s in sub.of("status")))
        n = len(cmd.results())
        bad = [
            (b'{"action":"clear","action":"inject","kind":1}', "duplicate key 'action'"),
            (b'{"action":"inject","kind":"encoder_loss","kind":"bus_off"}', "duplicate key 'kind'"),
            (b'{"action":"inject","kind":1,"id":"a","id":"b"}', "duplicate key 'id'"),
            (b'{"action":"inject","kind":6,"magnitude":1e308}', "magnitude: must be"),
            (b'{"action":"inject","kind":6,"magnitude":-1e308}', "magnitude: must be"),
            (b'{"action":"inject","kind":6,"magnitude":2147483648}', "magnitude: must be"),
            (b'{"action":"inject","kind":6,"magnitude":-2147483649}', "magnitude: must be"),
            (b'{"action":"inject","kind":6,"magnitude":1' + b"0" * 400 + b"}", "magnitude: "),
        ]
        for payload, _ in bad:
            cmd.publish(payload)
        sub.wait(lambda: len(cmd.results()) >= n + len(bad))
        got = cmd.results()[n:]
        assert len(got) == len(bad), got
        for (payload, words), res in zip(bad, got, strict=True):
            assert res["ok"] is False and words in res["error"], (payload, res)
            assert "active" not in res and "abort_code" not in res, (payload, res)
        # nothing was injected: a clear reports no active kind, the drive is not in FAULT
        cmd.publish({"action": "clear", "id": "after"})
        after = cmd.result("after")
        assert after["ok"] is True and after["active"] == [], after
        assert not any(s["cia402_state"] == "FAULT" for s in sub.of("state"))
        # the i32 limits themselves are accepted
        cmd.publish({"action": "inject", "kind": "following_error", "magnitude": 2147483647, "id": "max"})
        assert cmd.result("max")["ok"] is True
        cmd.publish({"action": "inject", "kind": "limit_switch", "magnitude": -2147483648, "id": "min"})
        assert cmd.result("min")["ok"] is True
        assert srv.proc.poll() is None
    assert srv.returncode == 0, srv.stderr[-2000:]
    assert "Traceback" not in srv.stderr
    cmd.sub.close()


def _serve(*args: str, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, "serve", "--can", "udp_multicast:239.74.163.9,port=47999", "--duration", "0.5",
                           "--status-interval", "0", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout_s)


def test_topic_levels_take_only_letters_digits_and_three_marks():
    from virtualaxis.services.mqtt import topic_name_problem

    for bad in ["X/#", "X/Y", "+", "#", "X+", "a b", "Ä", "$SYS", "", "X\n", "X\x00", "/", "X#Y"]:
        assert topic_name_problem(bad) is not None, bad
    for good in ["X", "x_1", "A-b.C", "0"]:
        assert topic_name_problem(good) is None, good


@pytest.mark.parametrize("name", ["X/#", "+", "a b"])
def test_an_axis_name_that_is_no_topic_level_is_refused_at_start_with_mqtt(name):
    r = _serve("--axis", f"{name}=1:configs/seed000-hust.toml", "--mqtt", "mqtt://127.0.0.1:1")
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --axis ") and "MQTT topic" in lines[0], r.stderr
    assert "internal error" not in r.stderr and not r.stdout.startswith("ready:")


@pytest.mark.parametrize("name", ["X/#", "X\nerror: forged"])
def test_a_config_axis_name_that_is_refused_names_the_config(tmp_path, name):
    body = (ROOT_PATH / "configs" / "seed000-hust.toml").read_text()
    assert '\nname = "seed000-hust"\n' in body
    cfg = tmp_path / "axis.toml"
    cfg.write_text(body.replace('\nname = "seed000-hust"\n', f"\nname = {json.dumps(name)}\n", 1))
    r = _serve("--config", str(cfg), "--mqtt", "mqtt://127.0.0.1:1")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {cfg}: axis.name: "), lines
    assert "forged" not in r.stdout and "ready:" not in r.stdout


@pytest.mark.parametrize("name", ["X\nerror: forged", "X\x1b[2J"])
def test_an_axis_name_with_a_control_character_is_refused_and_prints_no_forged_line(name):
    r = _serve("--axis", f"{name}=1:configs/seed000-hust.toml")
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --axis ") and "control character" in lines[0], lines
    assert "forged" not in r.stdout and "ready:" not in r.stdout


def test_a_good_name_still_serves():
    r = _serve("--axis", "X_1.a-b=1:configs/seed000-hust.toml")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("ready: serving X_1.a-b (node 1)")
