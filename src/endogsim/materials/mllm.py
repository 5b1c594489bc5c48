"""MLLM-guided material initialisation through any OpenAI-compatible chat-completions endpoint.

Per object we send two images (the frame with the object outlined, and a masked crop) and ask for one JSON
object that :class:`MLLMAnswer` validates. The answer is converted to SI units and checked against the prior
table (the class range widened by ``plausibility_factor``); a rejected answer is retried at most
``max_attempts - 1`` times with a stricter instruction, then the prior is used and a warning says why.

Privacy and safety: the API key is read from an environment variable only (``ENDOGSIM_MLLM_API_KEY``, then
``OPENAI_API_KEY``), is never written to the cache, a log or an error message (exception texts are scrubbed),
and images go only to the configured ``base_url``. Timeouts and retries are bounded by the client config;
one initialisation shares an :class:`MLLMBudget`: after a connection error or timeout the endpoint is not
asked again (every later object takes the prior at once), and all requests together stay within
``total_timeout_s``. Each record's ``source`` says where its value really came from.
Every answer is cached on disk, keyed by (model, prompt version, image hash, prompt text hash), so the
``replay`` backend reproduces a run offline.
"""

from __future__ import annotations

import base64
import hashlib
import json
import math
import os
import re
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pydantic import BaseModel, Field, ValidationError

from endogsim.errors import MaterialError
from endogsim.io.atomic import write_json_atomic
from endogsim.materials.field import MaterialRecord
from endogsim.materials.prior import prior_entry, prior_record

PROMPT_VERSION = "endogsim-material-v1"
API_KEY_ENVS = ("ENDOGSIM_MLLM_API_KEY", "OPENAI_API_KEY")

# Conversion factors to Pa; keys are lower-case because "mpa" in an answer always means megapascal here.
UNIT_TO_PA = {
    "pa": 1.0, "n/m^2": 1.0, "n/m2": 1.0, "kpa": 1e3, "mpa": 1e6, "n/mm^2": 1e6, "n/mm2": 1e6, "gpa": 1e9,
    "psi": 6894.757293168, "ksi": 6894757.293168,
}

REGIME_TEXT = {
    "in_vivo": "the IN VIVO small-strain regime (indentation, compression or elastography of living tissue; "
    "soft organs are typically 0.5-20 kPa)",
    "ex_vivo_tensile": "the EX VIVO TENSILE regime (uniaxial or biaxial tensile tests of excised organ walls at "
    "large stretch; typically 0.1-10 MPa)",
}


class MLLMFallbackWarning(UserWarning):
    """An MLLM answer could not be used; the prior value was taken instead."""


class ModulusAnswer(BaseModel):
    value: float
    unit: str
    min: float | None = None
    max: float | None = None


class MLLMAnswer(BaseModel):
    """The JSON object the model must return (E in the unit it names, density in kg/m^3)."""

    rationale: str
    category: str
    rigid: bool
    material_model: str
    E: ModulusAnswer
    nu: float
    density: float
    confidence: float = Field(ge=0.0, le=1.0)


@dataclass
class MLLMConfig:
    """Where and how to ask.

    Attributes:
        model: model name sent to the endpoint ("gpt-4o", "qwen2.5-vl-7b", ...).
        base_url: OpenAI-compatible endpoint (None = api.openai.com). Images are sent here and nowhere else.
        timeout_s: per-request client timeout in seconds.
        total_timeout_s: bound on the seconds of all requests of one initialisation (see :class:`MLLMBudget`).
        max_retries: client-side retries of connection errors, timeouts, HTTP 408/409/429/5xx (with backoff).
        max_attempts: answers requested per object (1 + at most 2 stricter retries).
        plausibility_factor: accepted E lies in [E_min / f, E_max * f] of the prior class range.
        cache_dir: answer cache folder.
        max_tokens: answer length limit.
    """

    model: str = "gpt-4o"
    base_url: str | None = None
    timeout_s: float = 60.0
    total_timeout_s: float = 300.0
    max_retries: int = 2
    max_attempts: int = 3
    plausibility_factor: float = 10.0
    cache_dir: str | Path = Path.home() / ".cache" / "endogsim" / "mllm"
    max_tokens: int = 600


class MLLMBudget:
    """What the queries of one initialisation share: a deadline (``total_timeout_s`` from its start) and, once
    the endpoint failed to connect or answer in time, the reason every later query skips it (fail fast)."""

    def __init__(self, total_timeout_s: float) -> None:
        self.total_timeout_s = total_timeout_s
        self.deadline = time.monotonic() + total_timeout_s
        self.unreachable: str | None = None

    def remaining(self) -> float:
        """Seconds left before the deadline (<= 0: used up)."""
        return self.deadline - time.monotonic()

    def skip_reason(self) -> str | None:
        """Why the endpoint is not to be asked any more, or None."""
        if self.unreachable is not None:
            return f"endpoint unreachable ({self.unreachable})"
        if self.remaining() <= 0:
            return f"the MLLM time budget of {self.total_timeout_s:g} s is used up"
        return None


# ---- key handling ---------------------------------------------------------------------------------------------------
def api_key_from_env(base_url: str | None) -> str:
    """The API key from the environment. Local servers usually need none, so a placeholder is used there."""
    for name in API_KEY_ENVS:
        v = os.environ.get(name)
        if v:
            return v
    if base_url and re.match(r"https?://(127\.0\.0\.1|localhost|\[::1\]|0\.0\.0\.0)(:|/|$)", base_url):
        return "no-key-needed"
    raise MaterialError(f"the mllm backend needs an API key in the environment variable {API_KEY_ENVS[0]} "
                        f"(or {API_KEY_ENVS[1]}); set it there, never in a file")


def scrub(text: str, key: str | None) -> str:
    """``text`` with the API key (and any bearer token) removed."""
    if key and len(key) >= 4:
        text = text.replace(key, "***")
    return re.sub(r"(?i)(bearer\s+)\S+", r"\1***", text)


# ---- images ---------------------------------------------------------------------------------------------------------
def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(rgb, dtype=np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _png(rgb_u8: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb_u8, cv2.COLOR_RGB2BGR))
    if not ok:
        raise MaterialError("could not encode an object image as PNG")
    return buf.tobytes()


def object_images(frame: np.ndarray, mask: np.ndarray, pad: int = 8) -> tuple[bytes, bytes]:
    """Two PNGs for one object.

    Args:
        frame: [H, W, 3] float RGB in [0, 1].
        mask: [H, W] bool, the object's pixels.
    Returns:
        (frame with the object's contour drawn in green, crop of the object's bounding box with the
        rest of the frame blacked out), PNG bytes.
    """
    img = _to_uint8(frame)
    m = mask.astype(np.uint8)
    if m.sum() == 0:
        raise MaterialError("object mask is empty in the chosen frame")
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    outlined = img.copy()
    cv2.drawContours(outlined, contours, -1, (0, 255, 0), thickness=max(2, img.shape[0] // 150))
    ys, xs = np.nonzero(m)
    y0, y1 = max(ys.min() - pad, 0), min(ys.max() + pad + 1, img.shape[0])
    x0, x1 = max(xs.min() - pad, 0), min(xs.max() + pad + 1, img.shape[1])
    crop = (img * m[..., None])[y0:y1, x0:x1]
    return _png(outlined), _png(crop)


def data_url(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


# ---- prompt ---------------------------------------------------------------------------------------------------------
SCHEMA_TEXT = (
    '{"rationale": str, "category": str (tissue or instrument class), "rigid": bool, '
    '"material_model": "neo_hookean" | "fixed_corotated" | "rigid" | "fluid", '
    '"E": {"value": number, "unit": "Pa" | "kPa" | "MPa" | "GPa" | "psi", "min": number, "max": number}, '
    '"nu": number (Poisson ratio, -1 < nu < 0.5), "density": number (kg/m^3), "confidence": number in [0, 1]}'
)


def build_messages(name: str, klass: str, regime: str, images: tuple[bytes, bytes], stricter: list[str]) -> list[dict]:
    system = (
        "You are a biomechanics expert helping to build a physics simulation of a laparoscopic surgery scene. "
        "You estimate material parameters of one object (a tissue or a surgical instrument) from images. "
        f"Young's modulus must be given for {REGIME_TEXT[regime]}. Surgical instruments are rigid steel or "
        "titanium. Reply with ONE JSON object and nothing else, with exactly these fields: " + SCHEMA_TEXT
    )
    text = (
        f"Image 1: an endoscopic frame with the object outlined in green. Image 2: a crop of the object with "
        f"everything else blacked out. The segmentation label says: name {name!r}, class {klass!r}. "
        "Estimate its material parameters."
    )
    msgs: list[dict] = [
        {"role": "system", "content": system},
        {"role": "user", "content": [
            {"type": "text", "text": text},
            {"type": "image_url", "image_url": {"url": data_url(images[0])}},
            {"type": "image_url", "image_url": {"url": data_url(images[1])}},
        ]},
    ]
    for reason in stricter:
        msgs.append({"role": "user", "content": (
            f"Your previous answer was rejected: {reason}. Answer again with ONLY one JSON object (no prose, no "
            f"code fence) with exactly the fields {SCHEMA_TEXT}. E must be for {REGIME_TEXT[regime]}.")})
    return msgs


# ---- answer checking ------------------------------------------------------------------------------------------------
def extract_json(content: str) -> dict:
    """The JSON object in a reply, tolerating a ```json fence or text around it."""
    s = content.strip()
    fence = re.search(r"```(?:json)?\s*(.*?)```", s, re.S)
    if fence:
        s = fence.group(1).strip()
    if not s.startswith("{"):
        i, j = s.find("{"), s.rfind("}")
        if i < 0 or j <= i:
            raise ValueError("no JSON object in the reply")
        s = s[i : j + 1]
    obj = json.loads(s)
    if not isinstance(obj, dict):
        raise ValueError("the reply is JSON but not an object")
    return obj


def to_pascal(value: float, unit: str) -> float:
    u = unit.strip().lower().replace(" ", "").replace("²", "^2")
    if u not in UNIT_TO_PA:
        raise ValueError(f"unknown unit {unit!r} for E (use Pa, kPa, MPa, GPa or psi)")
    return float(value) * UNIT_TO_PA[u]


def _model_name(s: str, rigid: bool) -> str:
    s = s.lower()
    if rigid or "rigid" in s:
        return "rigid"
    if "corot" in s:
        return "fixed_corotated"
    if "fluid" in s:
        return "fluid"
    return "neo_hookean"


def answer_to_record(
    content: str, object_id: int, name: str, klass: str, is_tool: bool, regime: str, factor: float, source: str
) -> MaterialRecord:
    """Parse, convert and check one reply; raises ValueError with the reason it is unusable."""
    try:
        ans = MLLMAnswer.model_validate(extract_json(content))
    except json.JSONDecodeError as exc:
        raise ValueError(f"malformed JSON ({exc.msg})") from None
    except ValidationError as exc:
        raise ValueError(f"JSON does not match the schema ({exc.error_count()} errors: "
                         f"{'; '.join(e['loc'][0].__str__() + ': ' + e['msg'] for e in exc.errors()[:3])})") from None
    E = to_pascal(ans.E.value, ans.E.unit)
    E_min = to_pascal(ans.E.min, ans.E.unit) if ans.E.min is not None else None
    E_max = to_pascal(ans.E.max, ans.E.unit) if ans.E.max is not None else None
    if E_min is not None and E_max is not None and E_min > E_max:
        E_min, E_max = E_max, E_min
    key, entry = prior_entry(klass, is_tool)
    prior_rigid = bool(entry["rigid"]) or is_tool
    if ans.rigid != prior_rigid:
        raise ValueError(f"rigid = {ans.rigid} but the label says this is {'an instrument' if prior_rigid else 'tissue'}")
    lo, hi = entry[regime]["E_min"] / factor, entry[regime]["E_max"] * factor
    if not (math.isfinite(E) and lo <= E <= hi):
        raise ValueError(f"E = {E:.3g} Pa is implausible for {key} in the {regime} regime "
                         f"(accepted {lo:.3g} to {hi:.3g} Pa)")
    nu = ans.nu
    if 0.49 <= nu <= 0.5:  # "incompressible" answers: keep inside the open interval the simulator needs
        nu = min(nu, 0.499)
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"nu = {ans.nu} is outside (-1, 0.5)")
    if not (300.0 <= ans.density <= 25000.0):
        raise ValueError(f"density = {ans.density} is not a plausible value in kg/m^3")
    if E_min is not None and not (E_min > 0):
        E_min = None
    if E_max is not None and not (E_max > 0):
        E_max = None
    return MaterialRecord(
        name=name, object_id=object_id, klass=klass, model=_model_name(ans.material_model, prior_rigid),  # type: ignore[arg-type]
        rigid=prior_rigid, E=E, nu=nu, density=ans.density, E_min=E_min, E_max=E_max, source=source,
        confidence=ans.confidence, regime=regime,  # type: ignore[arg-type]
    )


# ---- cache ----------------------------------------------------------------------------------------------------------
def cache_key(model: str, image_hash: str, prompt_text: str) -> str:
    h = hashlib.sha256(json.dumps([model, PROMPT_VERSION, image_hash, prompt_text]).encode()).hexdigest()
    return h[:32]


def _cache_path(cache_dir: str | Path, key: str) -> Path:
    return Path(cache_dir) / f"{key}.json"


def read_cache(cache_dir: str | Path, key: str) -> dict | None:
    p = _cache_path(cache_dir, key)
    if not p.exists():
        return None
    try:
        return json.loads(p.read_text())
    except json.JSONDecodeError:
        return None


def write_cache(cache_dir: str | Path, key: str, entry: dict, api_key: str | None = None) -> None:
    """Atomic JSON write; every string is scrubbed of the API key first (a server could echo it)."""

    write_json_atomic(_cache_path(cache_dir, key), json.loads(scrub(json.dumps(entry), api_key)))


# ---- the query ------------------------------------------------------------------------------------------------------
@dataclass
class ObjectQuery:
    """One object to ask about: label fields plus its two images (PNG bytes)."""

    object_id: int
    name: str
    klass: str
    is_tool: bool
    images: tuple[bytes, bytes]

    @property
    def image_hash(self) -> str:
        return hashlib.sha256(self.images[0] + b"|" + self.images[1]).hexdigest()

    def prompt_text(self, regime: str) -> str:
        return f"{self.name}|{self.klass}|{regime}"


def _fallback(q: ObjectQuery, regime: str, reason: str, key: str | None) -> MaterialRecord:
    reason = scrub(reason, key)
    warnings.warn(f"object {q.object_id} ({q.name}): MLLM answer not used ({reason}); using the prior",
                  MLLMFallbackWarning, stacklevel=3)
    return prior_record(q.object_id, q.name, q.klass, q.is_tool, regime, source=f"prior (mllm fallback: {reason})")


def make_client(cfg: MLLMConfig) -> tuple[Any, str]:
    """An ``openai.OpenAI`` client with bounded timeout and retries, and the key it uses (kept in memory only)."""
    import openai

    key = api_key_from_env(cfg.base_url)
    client = openai.OpenAI(api_key=key, base_url=cfg.base_url, timeout=cfg.timeout_s, max_retries=cfg.max_retries)
    return client, key


def query_object(q: ObjectQuery, cfg: MLLMConfig, regime: str = "in_vivo", client: Any = None,
                 replay: bool = False, budget: MLLMBudget | None = None) -> MaterialRecord:
    """The material of one object from the MLLM (or, with ``replay``, from the cache only).

    ``budget``: shared by the objects of one initialisation (fail fast, bounded total time); None: this
    query alone, bounded by the client's timeout and retries.
    """
    key = cache_key(cfg.model, q.image_hash, q.prompt_text(regime))
    cached = read_cache(cfg.cache_dir, key)
    if replay:
        if cached is None:
            raise MaterialError(
                f"replay: no cached MLLM answer for object {q.object_id} ({q.name}) with model {cfg.model!r} and "
                f"prompt {PROMPT_VERSION} in {cfg.cache_dir} (cache key {key}); run the mllm backend first")
        if cached.get("status") == "ok":
            return answer_to_record(cached["answer"], q.object_id, q.name, q.klass, q.is_tool, regime,
                                    cfg.plausibility_factor, source=f"replay:{cfg.model}")
        return _fallback(q, regime, f"replayed: {cached.get('reason', 'no usable answer')}", None)
    if cached is not None and cached.get("status") == "ok":
        return answer_to_record(cached["answer"], q.object_id, q.name, q.klass, q.is_tool, regime,
                                cfg.plausibility_factor, source=f"mllm:{cfg.model} (cached)")
    budget = budget or MLLMBudget(math.inf)
    if budget.skip_reason():
        return _fallback(q, regime, budget.skip_reason(), None)

    import openai

    api_key = None
    if client is None:
        client, api_key = make_client(cfg)
    else:
        api_key = getattr(client, "api_key", None)
    attempts: list[dict] = []
    reasons: list[str] = []
    json_mode = True
    for _ in range(max(1, cfg.max_attempts)):
        if budget.skip_reason():
            reasons.append(budget.skip_reason())
            break
        msgs = build_messages(q.name, q.klass, regime, q.images, reasons)
        # every try of the client (1 + max_retries) within what is left of the budget
        timeout = min(cfg.timeout_s, budget.remaining() / (1 + cfg.max_retries))
        try:
            try:
                resp = client.chat.completions.create(
                    model=cfg.model, messages=msgs, temperature=0.0, max_tokens=cfg.max_tokens, timeout=timeout,
                    **({"response_format": {"type": "json_object"}} if json_mode else {}),
                )
            except openai.BadRequestError:
                if not json_mode:
                    raise
                # Some local servers reject response_format; the prompt alone asks for JSON, so ask once without.
                json_mode = False
                resp = client.chat.completions.create(
                    model=cfg.model, messages=msgs, temperature=0.0, max_tokens=cfg.max_tokens, timeout=timeout)
        except openai.APIConnectionError as exc:  # also timeouts: the endpoint is not asked again
            budget.unreachable = f"{type(exc).__name__}: {scrub(str(exc), api_key)}"
            return _fallback(q, regime, budget.unreachable, api_key)
        except openai.APIError as exc:
            # Transport failures were already retried (bounded) by the client: give up on this object.
            return _fallback(q, regime, f"{type(exc).__name__}: {scrub(str(exc), api_key)}", api_key)
        except ValueError as exc:  # a body that is not JSON although the server says it is
            return _fallback(q, regime, f"the endpoint did not answer in the chat-completions format "
                                        f"({type(exc).__name__})", api_key)
        if not hasattr(resp, "choices"):  # e.g. an HTML page served with status 200
            return _fallback(q, regime, f"the endpoint did not answer in the chat-completions format (got "
                                        f"{scrub(str(resp), api_key)[:60]!r})", api_key)
        if not resp.choices:
            reasons.append("empty reply (no choices)")
            continue
        choice = resp.choices[0]
        content = choice.message.content or ""
        refusal = getattr(choice.message, "refusal", None)
        attempts.append({"finish_reason": choice.finish_reason, "content": content, "refusal": refusal})
        if refusal:
            reasons.append(f"the model refused ({refusal[:200]})")
            continue
        if choice.finish_reason == "length":
            reasons.append("the answer was truncated (finish_reason 'length')")
            continue
        try:
            rec = answer_to_record(content, q.object_id, q.name, q.klass, q.is_tool, regime,
                                   cfg.plausibility_factor, source=f"mllm:{cfg.model}")
        except (ValueError, MaterialError) as exc:
            reasons.append(str(exc))
            continue
        write_cache(cfg.cache_dir, key, {"status": "ok", "model": cfg.model, "prompt_version": PROMPT_VERSION,
                                         "image_hash": q.image_hash, "object": q.name, "regime": regime,
                                         "answer": content, "attempts": attempts}, api_key)
        return rec
    reason = reasons[-1] if reasons else "no answer"
    write_cache(cfg.cache_dir, key, {"status": "fallback", "reason": scrub(reason, api_key), "model": cfg.model,
                                     "prompt_version": PROMPT_VERSION, "image_hash": q.image_hash, "object": q.name,
                                     "regime": regime, "attempts": attempts}, api_key)
    return _fallback(q, regime, f"{len(attempts)} answers rejected, last: {reason}", api_key)
