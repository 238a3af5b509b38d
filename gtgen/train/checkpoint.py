"""The checkpoint file: one ``torch.save`` dict, written atomically, with a checksum of
the weights so that a damaged file is an error rather than a model of garbage.

The dict holds ``version`` (``CKPT_VERSION``), ``preset``, ``train`` and ``data_config``
(the resolved configs), ``model`` (state dict), ``optim``, ``sched``, ``scaler``, ``step``,
``history`` (the logged steps), ``best`` (the best validation so far), ``dataset`` (the
record of the dataset it was trained on: ``train.runs``) and ``model_sha256``.
"""

from __future__ import annotations

import hashlib
import io
from pathlib import Path

import torch

from gtgen.config import GtgenConfig, TrainConfig, stored_config
from gtgen.errors import TrainError
from gtgen.runtime.output import signature, write_atomic

# 2: heads correct a smoothed min-z prior; 3: the prior filled everywhere is an input, four-level U-Net;
# 4: the prior filled on a pyramid, the micro prior at the points grid's resolution, images as bytes;
# 5: pillars capped per pillar and per sample, chunked BEV pooling, EfficientNet-B0 image branch
#    (paper preset), the micro crop over exactly the centre half, a weights checksum, AMP scaler
CKPT_VERSION = 5


def weights_digest(state: dict[str, torch.Tensor]) -> str:
    """Return the SHA-256 of a state dict's names and tensor bytes, in name order."""
    h = hashlib.sha256()
    for k in sorted(state):
        v = state[k]
        h.update(k.encode())
        h.update(str(tuple(v.shape)).encode() + str(v.dtype).encode())
        h.update(v.detach().cpu().contiguous().view(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


def save_checkpoint(path: Path, payload: dict, overwrite: bool = False) -> None:
    """Write ``payload`` (with its weights' digest added) to ``path`` atomically (a file
    there that gtgen did not write only with ``overwrite``). It is
    serialised in memory first, so that a full disk is the atomic writer's one-line error
    (torch.save into a file reports it as a generic RuntimeError)."""
    # the signature first, near the file's start: a later save may replace it (runtime.output.owned)
    payload = {"written_by": signature(), **payload, "version": CKPT_VERSION, "model_sha256": weights_digest(payload["model"])}
    buf = io.BytesIO()
    torch.save(payload, buf)
    write_atomic(path, buf.getbuffer(), overwrite)


def load_checkpoint(path: Path, preset: str | None = None) -> tuple[dict, TrainConfig, GtgenConfig]:
    """Return a checkpoint's state with its validated train and data configs. Raises
    TrainError (one line) for a missing, unreadable, truncated or damaged file, another
    version, another preset than ``preset``, or configs this gtgen does not accept."""
    if path.is_dir():
        raise TrainError(f"checkpoint '{path}' is a folder, not a checkpoint file (ckpt.pt or best.pt in a run folder)")
    if not path.is_file():
        raise TrainError(f"checkpoint '{path}' does not exist")
    try:  # as data only (tensors, numbers, strings): a file from elsewhere never runs code
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001 - torch raises many types for bad files
        raise TrainError(f"checkpoint '{path}' cannot be read (truncated or not a checkpoint): {err}".splitlines()[0]) from err
    if not isinstance(state, dict) or state.get("version") != CKPT_VERSION:
        found = state.get("version") if isinstance(state, dict) else type(state).__name__
        raise TrainError(f"'{path}' is not a gtgen checkpoint of version {CKPT_VERSION} (found {found!r}); retrain with this version")
    model = state.get("model")
    if not isinstance(model, dict) or state.get("model_sha256") != weights_digest(model):
        raise TrainError(f"checkpoint '{path}' is damaged: its weights do not match their checksum; use another checkpoint or retrain")
    if preset is not None and state.get("preset") != preset:
        raise TrainError(f"checkpoint '{path}' is of preset {state.get('preset')!r}; expected {preset!r}")
    from pydantic import ValidationError

    try:
        return state, TrainConfig.model_validate(state["train"]), stored_config(state["data_config"], f"checkpoint '{path}'")
    except (KeyError, ValidationError) as err:
        first = err.errors()[0] if isinstance(err, ValidationError) else {"loc": (str(err),), "msg": "missing"}
        where = ".".join(str(x) for x in first["loc"])
        raise TrainError(f"checkpoint '{path}' holds a config this gtgen does not accept ({where}: {first['msg']}); retrain with this version") from err
