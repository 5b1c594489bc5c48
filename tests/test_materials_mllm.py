"""MLLM backend against a local fake chat-completions server, with the real ``openai`` client.

The server (http.server in a thread, 127.0.0.1, ephemeral port) plays a script of replies, one per request.
"""

from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from endogsim.errors import MaterialError
from endogsim.io.scene import ObjectLabel, Scene
from endogsim.materials import MaterialInitConfig, MLLMConfig, MLLMFallbackWarning, initialise_materials
from endogsim.materials.mllm import to_pascal

KEY = "sk-test-S3CRET-key-0123456789"
MODEL = "fake-vlm"


def answer(E=4.5, unit="kPa", rigid=False, model="neo_hookean", nu=0.47, density=1060.0, conf=0.7, **extra):
    d = {"rationale": "smooth dark red organ", "category": "liver", "rigid": rigid, "material_model": model,
         "E": {"value": E, "unit": unit, "min": E / 2, "max": E * 2}, "nu": nu, "density": density,
         "confidence": conf}
    d.update(extra)
    return json.dumps(d)


class FakeServer:
    """Replies from ``script`` in order (the last entry repeats). Each entry: dict with keys status, content,
    finish_reason, refusal, delay, headers, body."""

    def __init__(self) -> None:
        self.script: list[dict] = []
        self.requests: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):  # keep test output quiet
                pass

            def do_POST(self):
                body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
                outer.requests.append({"path": self.path, "body": body, "auth": self.headers.get("Authorization")})
                step = outer.script[min(len(outer.requests) - 1, len(outer.script) - 1)]
                if step.get("delay"):
                    time.sleep(step["delay"])
                status = step.get("status", 200)
                if "body" in step:
                    payload = step["body"]
                elif status == 200:
                    payload = {"id": "chatcmpl-1", "object": "chat.completion", "created": 0, "model": body["model"],
                               "choices": [{"index": 0, "finish_reason": step.get("finish_reason", "stop"),
                                            "message": {"role": "assistant", "content": step.get("content"),
                                                        "refusal": step.get("refusal")}}],
                               "usage": {"prompt_tokens": 1, "completion_tokens": 1, "total_tokens": 2}}
                else:
                    payload = {"error": {"message": f"status {status}", "type": "server_error"}}
                data = json.dumps(payload).encode()
                try:
                    self.send_response(status)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(data)))
                    for k, v in step.get("headers", {}).items():
                        self.send_header(k, v)
                    self.end_headers()
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):  # the client timed out and left
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/v1"
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


@pytest.fixture
def server():
    s = FakeServer()
    yield s
    s.close()


@pytest.fixture(autouse=True)
def _key(monkeypatch):
    monkeypatch.setenv("ENDOGSIM_MLLM_API_KEY", KEY)


def make_scene() -> Scene:
    """32x32, two frames: a liver blob (id 1) and a grasper bar (id 2); -1 elsewhere."""
    rng = np.random.default_rng(0)
    frames = rng.uniform(0.2, 0.8, size=(2, 32, 32, 3)).astype(np.float32)
    masks = np.full((2, 32, 32), -1, np.int32)
    yy, xx = np.mgrid[:32, :32]
    masks[:, (yy - 12) ** 2 + (xx - 12) ** 2 < 60] = 1
    masks[1, 24:28, 4:30] = 2
    labels = {1: ObjectLabel(1, "liver", False, "liver"), 2: ObjectLabel(2, "grasper", True, "grasper")}
    return Scene(frames=frames, times=np.array([0.0, 0.04]), K=np.eye(3), object_masks=masks, labels=labels,
                 source="synthetic")


def run(server, tmp_path, script, objects=(1,), backend="mllm", **cfg_kw):
    server.script = script
    scene = make_scene()
    labels = {i: scene.labels[i] for i in objects}
    mcfg = MLLMConfig(model=MODEL, base_url=server.url, cache_dir=tmp_path / "cache",
                      timeout_s=cfg_kw.pop("timeout_s", 5.0), max_retries=cfg_kw.pop("max_retries", 2), **cfg_kw)
    return initialise_materials(labels, MaterialInitConfig(backend=backend, mllm=mcfg), scene)


def test_valid_answer_parsed_and_images_sent(server, tmp_path):
    f = run(server, tmp_path, [{"content": answer(E=4.5, unit="kPa")}])
    r = f[1]
    assert r.E == pytest.approx(4500.0) and r.nu == pytest.approx(0.47) and r.density == 1060.0
    assert r.source == f"mllm:{MODEL}" and r.confidence == pytest.approx(0.7) and not r.rigid
    assert r.E_min == pytest.approx(2250.0) and r.E_max == pytest.approx(9000.0)
    req = server.requests[0]
    assert len(server.requests) == 1 and req["path"].endswith("/chat/completions") and req["body"]["model"] == MODEL
    urls = [c["image_url"]["url"] for c in req["body"]["messages"][1]["content"] if c["type"] == "image_url"]
    assert len(urls) == 2 and all(u.startswith("data:image/png;base64,") for u in urls)
    assert "IN VIVO" in req["body"]["messages"][0]["content"]


def test_refusal_retried_twice_then_prior(server, tmp_path):
    with pytest.warns(MLLMFallbackWarning, match="refused"):
        f = run(server, tmp_path, [{"content": None, "refusal": "I can't help with medical images."}])
    assert len(server.requests) == 3  # first try + at most two stricter retries
    assert "previous answer was rejected" in json.dumps(server.requests[1]["body"]["messages"][-1])
    r = f[1]
    assert r.source.startswith("prior (mllm fallback:") and r.E == 5e3  # liver in vivo prior


def test_malformed_json_then_valid(server, tmp_path):
    f = run(server, tmp_path, [{"content": '{"rationale": "x", "E": {"value": 4'}, {"content": answer(E=6, unit="kPa")}])
    assert f[1].E == pytest.approx(6000.0) and len(server.requests) == 2


def test_gpa_for_tool_is_converted(server, tmp_path):
    f = run(server, tmp_path, [{"content": answer(E=200, unit="GPa", rigid=True, model="rigid", nu=0.3, density=7900)}],
            objects=(2,))
    r = f[2]
    assert r.E == pytest.approx(2e11) and r.rigid and r.model == "rigid" and r.source == f"mllm:{MODEL}"


def test_gpa_for_tissue_is_implausible_retry_then_fallback(server, tmp_path):
    f = run(server, tmp_path, [{"content": answer(E=3, unit="GPa")}, {"content": answer(E=8, unit="kPa")}])
    assert f[1].E == pytest.approx(8000.0) and len(server.requests) == 2
    assert "implausible" in json.dumps(server.requests[1]["body"]["messages"][-1])
    server.requests.clear()
    with pytest.warns(MLLMFallbackWarning, match="implausible"):
        f = run(server, tmp_path / "b", [{"content": answer(E=3, unit="GPa")}])
    assert f[1].E == 5e3 and "fallback" in f[1].source and len(server.requests) == 3


def test_truncated_answer_retried(server, tmp_path):
    f = run(server, tmp_path, [{"content": answer()[:40], "finish_reason": "length"}, {"content": answer(E=3, unit="kPa")}])
    assert f[1].E == pytest.approx(3000.0) and len(server.requests) == 2
    assert "truncated" in json.dumps(server.requests[1]["body"]["messages"][-1])


@pytest.mark.parametrize("status", [429, 500])
def test_http_error_then_success(server, tmp_path, status):
    f = run(server, tmp_path, [{"status": status, "headers": {"retry-after-ms": "20"}}, {"content": answer(E=7, unit="kPa")}])
    assert f[1].E == pytest.approx(7000.0) and len(server.requests) == 2 and f[1].source == f"mllm:{MODEL}"


def test_timeout_falls_back_quickly(server, tmp_path):
    t0 = time.perf_counter()
    with pytest.warns(MLLMFallbackWarning, match="Timeout"):
        f = run(server, tmp_path, [{"delay": 1.0, "content": answer()}], timeout_s=0.3, max_retries=0)
    assert time.perf_counter() - t0 < 3.0
    assert f[1].E == 5e3 and "fallback" in f[1].source


def test_cache_replays_without_server(server, tmp_path):
    f1 = run(server, tmp_path, [{"content": answer(E=4.5, unit="kPa")}, {"content": answer(E=200, unit="GPa", rigid=True,
             model="rigid", nu=0.3, density=7900)}], objects=(1, 2))
    assert len(server.requests) == 2
    # Same inputs again: answered from the cache, no request.
    f2 = run(server, tmp_path, [{"status": 500}], objects=(1, 2))
    assert len(server.requests) == 2 and f2[1].E == f1[1].E and "cached" in f2[1].source
    server.close()  # replay must not need the endpoint at all
    scene = make_scene()
    cfg = MaterialInitConfig(backend="replay", mllm=MLLMConfig(model=MODEL, base_url="http://127.0.0.1:9/v1",
                                                               cache_dir=tmp_path / "cache"))
    f3 = initialise_materials(scene.labels, cfg, scene)
    assert f3[1].E == f1[1].E and f3[2].E == f1[2].E and f3[1].source == f"replay:{MODEL}"
    cfg.mllm.model = "other-model"
    with pytest.raises(MaterialError, match="no cached MLLM answer"):
        initialise_materials(scene.labels, cfg, scene)
    server.httpd = _Dummy()  # fixture teardown closes again


class _Dummy:
    def shutdown(self):
        pass

    def server_close(self):
        pass


def test_key_never_written(server, tmp_path):
    # The server echoes the Authorization header in an error body; the key must still reach no file or message.
    echo = {"status": 400, "body": {"error": {"message": f"bad request from Bearer {KEY}", "type": "invalid"}}}
    with pytest.warns(MLLMFallbackWarning) as rec:
        f = run(server, tmp_path, [{"content": f"not json {KEY}"}, {"content": f"still not json {KEY}"}, echo],
                objects=(1,))
    assert server.requests[0]["auth"] == f"Bearer {KEY}"  # the key did reach the endpoint, in the header only
    f.save(tmp_path / "out" / "materials.json")
    assert all(KEY not in str(w.message) for w in rec)
    written = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert written
    for p in written:
        assert KEY not in p.read_text(), p


def test_key_scrubbed_from_cached_attempts(server, tmp_path):
    with pytest.warns(MLLMFallbackWarning):
        run(server, tmp_path, [{"content": f"no json here {KEY}"}])
    files = list((tmp_path / "cache").glob("*.json"))
    assert files and all(KEY not in p.read_text() for p in files)
    assert "***" in files[0].read_text()


def test_unit_conversion():
    assert to_pascal(1, "kPa") == 1e3 and to_pascal(2, "MPa") == 2e6 and to_pascal(1, "GPa") == 1e9
    assert to_pascal(5, "Pa") == 5 and to_pascal(1, "psi") == pytest.approx(6894.757)
    with pytest.raises(ValueError):
        to_pascal(1, "bar-ish")


def test_missing_key_for_hosted_endpoint(monkeypatch, tmp_path):
    monkeypatch.delenv("ENDOGSIM_MLLM_API_KEY", raising=False)
    monkeypatch.delenv("OPENAI_API_KEY", raising=False)
    scene = make_scene()
    cfg = MaterialInitConfig(backend="mllm", mllm=MLLMConfig(cache_dir=tmp_path))
    with pytest.raises(MaterialError, match="ENDOGSIM_MLLM_API_KEY"):
        initialise_materials(scene.labels, cfg, scene)


def test_server_without_json_mode(server, tmp_path):
    # A local server that rejects response_format once: the request is repeated without it.
    f = run(server, tmp_path, [{"status": 400}, {"content": "```json\n" + answer(E=2, unit="kPa") + "\n```"}])
    assert f[1].E == pytest.approx(2000.0)
    assert "response_format" in server.requests[0]["body"] and "response_format" not in server.requests[1]["body"]


def test_cli_mllm_then_replay(server, tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import endogsim.io
    from endogsim.cli.main import app
    from endogsim.materials import MaterialField

    # Stand-in for a data folder reader: the CLI only needs a Scene.
    monkeypatch.setattr(endogsim.io, "load_scene", lambda path, **kw: make_scene(), raising=False)
    data = tmp_path / "data"
    data.mkdir()
    server.script = [{"content": answer(E=4.5, unit="kPa")},
                     {"content": answer(E=200, unit="GPa", rigid=True, model="rigid", nu=0.3, density=7900)}]
    out = tmp_path / "run" / "materials.json"
    args = ["materials", "init", str(data), "--out", str(out), "--model", MODEL, "--base-url", server.url]
    r = CliRunner().invoke(app, args + ["--backend", "mllm"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert f"mllm:{MODEL}" in r.output and MaterialField.load(out)[1].E == pytest.approx(4500.0)
    n = len(server.requests)
    r = CliRunner().invoke(app, args + ["--backend", "replay", "--out", str(tmp_path / "run" / "replay.json")],
                           env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert len(server.requests) == n and MaterialField.load(tmp_path / "run" / "replay.json")[2].E == 2e11
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert any("mllm_cache" in str(p) for p in files)
    assert all(KEY not in p.read_text() for p in files) and KEY not in r.output
