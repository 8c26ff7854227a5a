"""The relightable avatar of one subject for the OLAT expansion: decoded when stage 1 knows the subject,
fitted (and kept on disk for re-runs) when it does not.

A stage-1 training subject is decoded from its own identity code with the OLAT dataset's lighting code, so
its Gaussians carry the colours stage 2 was trained on; no optimisation runs. Any other subject (a held-out
test subject, a subject of a dataset stage 1 never saw) is fitted to its full-on views by inversion and
finetuning (:class:`relightanyone.model.fit.fitter.Fitter`). The fitted avatar file records a fingerprint of
everything the fit depends on; a re-run loads it when the fingerprint matches and fits again otherwise.
"""

from __future__ import annotations

from pathlib import Path

import torch

from relightanyone.errors import InputError
from relightanyone.model.fit.avatar import FittedAvatar, decoded_avatar
from relightanyone.model.fit.fitter import Fitter
from relightanyone.model.fit.views import load_fit_views

__all__ = ["decoded_avatar", "fitted_avatar"]


def fitted_avatar(
    model,
    source_dir: Path,
    subject: str,
    frame: int,
    fit_settings,
    avatar_path: Path,
    fingerprint: str,
    image_scale: float = 1.0,
):
    """The fitted avatar of a subject stage 1 does not know: loaded from ``avatar_path`` when it was fitted
    with the same ``fingerprint``, else fitted to the subject's full-on views of ``frame`` and saved there.

    Args:
        model: :class:`~relightanyone.model.fit.fitter.RelightableModel` (never changed; the fit finetunes a
            copy on the model's device).
        fit_settings: :class:`~relightanyone.model.fit.fitter.FitSettings` (iterations, learning rates, seed).
        fingerprint: hex digest of the inputs of the fit (checkpoints, source rows, settings).
    """

    avatar_path = Path(avatar_path)
    if avatar_path.is_file():
        try:
            cached = FittedAvatar.load(avatar_path)
        except ValueError:
            cached = None  # unreadable (e.g. written by another version): fit again and replace it
        if cached is not None and cached.metadata.get("expand_fingerprint") == fingerprint:
            return cached
    views = load_fit_views(source_dir, subject, frame, None, "full", image_scale).to(model.device)
    template = model.stage1.mesh_decoder.template_vertices
    if views.tracked_vertices is not None and views.tracked_vertices.shape != template.shape:
        raise InputError(
            f"{source_dir}: tracked mesh of {subject!r} frame {frame} has {views.tracked_vertices.shape[0]} "
            f"vertices, the stage-1 template has {template.shape[0]}; the expansion needs one topology"
        )
    torch.manual_seed(fit_settings.seed)
    fitter = Fitter(model, views, fit_settings)
    fitter.invert()
    fitter.finetune()
    avatar = fitter.avatar({"data": str(Path(source_dir).resolve()), "expand_fingerprint": fingerprint})
    avatar_path.parent.mkdir(parents=True, exist_ok=True)
    avatar.save(avatar_path)
    # Render from the file, so a first run and a re-run that loads the avatar use the very same tensors.
    return FittedAvatar.load(avatar_path)
