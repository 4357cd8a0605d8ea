"""What the model families share in the viewer: the helpers their ``view`` modules build scenes
with, and :class:`TrainView` (``clsplat train ... --view``). Checkpoints and run folders become
scenes in :func:`clsplat.models.registry.scene_from_checkpoint` (what ``clsplat view`` /
``clsplat render`` show for them; the engine's ``clsplat.scene_readers`` entry point), through
each family's :meth:`~.command.Family.checkpoint_scene`:

* AutoSplat (a per-scene optimisation): the model is rebuilt from the checkpoint and the run's
  data (``metrics.json``'s ``data`` and ``scale``, else ``--data``), and the scene carries the
  recording's cameras with their images, the ego trajectory, the LiDAR points, the tracked boxes
  and a time slider that places the moving objects (with their residual SH) at each frame.
* DrivingForward and PGT (feed-forward): the network runs on held-out sample ``sample`` of
  ``data`` (default: the run's, where its ``metrics.json`` records it, else synthetic); the
  scene is its predicted Gaussians with the input cameras (and their images) and the predicted
  depth maps. :func:`model_snapshot` builds it in eval mode with the RNG restored, which is also
  how ``clsplat train FAMILY --view`` shows a model as it trains.
* A run folder without a checkpoint but with ``scene.ply`` shows the ``.ply``.

"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from clsplat.viewer.scene import ViewScene

__all__ = ["TrainView", "train_watcher", "model_snapshot", "run_data", "gaussians_scene",
           "depth_colour", "VARIANT_SAMPLES"]


def gaussians_scene(g, title: str) -> ViewScene:
    return ViewScene(g.means, g.quats, g.scales, g.opacities, g.sh, title=title)


def depth_colour(d: np.ndarray, far: float = 80.0) -> np.ndarray:
    """[H, W] metres -> [H, W, 3] turbo-like colours (near warm, far cool; inf/NaN black)."""
    ok = np.isfinite(d)
    t = np.clip(np.log1p(np.where(ok, d, far)) / np.log1p(far), 0, 1)
    rgb = np.stack([1 - t, 1 - np.abs(2 * t - 1), t], -1)
    rgb[~ok] = 0
    return rgb.astype(np.float32)


def model_snapshot(model: torch.nn.Module, build):
    """``build()`` (-> a :class:`ViewScene` of ``model``'s output) run with ``model`` in eval mode,
    without gradients and with torch's CPU RNG state restored afterwards; the model's mode is
    restored too. A training run watched with ``--view`` is thereby the same run unwatched."""
    was = model.training
    with torch.random.fork_rng(devices=[]), torch.no_grad():
        model.eval()
        try:
            return build()
        finally:
            model.train(was)


def run_data(run: Path) -> str | None:
    """The data a run trained on as its folder records it (``metrics.json``'s ``protocol.data``;
    runs before the shared schema kept it at the top level), else None."""
    import json

    m = Path(run) / "metrics.json"
    try:
        rec = json.loads(m.read_text()) if m.is_file() else {}
        d = rec.get("protocol", {}).get("data") or rec.get("data")
    except (OSError, ValueError, AttributeError):
        return None
    return d if isinstance(d, str) and d else None


#: samples of the held-out split a feed-forward checkpoint's viewer offers
VARIANT_SAMPLES = 4


class TrainView:
    """``clsplat train ... --view``: serve a run's scene while it trains.

    The viewer starts at the first step (once the model has Gaussians). While a browser is
    connected, every ``every`` steps (and when a browser connects) the Gaussians shown (and the
    depth maps, where the scene has them) are replaced by the model's current ones and the loss
    plot is updated; the exact renders run in
    the training thread between steps (one thread uses the OpenCL device). With no browser a step
    costs a list append and a look at the client table.

    Args:
        scene_fn: ``() -> ViewScene`` of the model now.
        host, port: where to listen; every: steps between refreshes; device: exact-render device.
    """

    def __init__(self, scene_fn, host: str = "127.0.0.1", port: int = 8080, every: int = 10, device=None) -> None:
        from clsplat.viewer.server import check_port_free
        import viser  # noqa: F401  (the view extra, named by clsplat.cli when missing)

        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ValueError(f"--view-every: expected a positive number of steps, got {every!r}")
        check_port_free(host, port, ("--view-host", "--view-port"))
        self.scene_fn, self.host, self.port, self.every, self.device = scene_fn, host, port, every, device
        self.viewer = None
        self.plot = None
        self.steps: list[int] = []
        self.losses: list[float] = []
        self._seen: set[int] = set()
        self.refreshes = 0

    def start(self) -> None:
        from clsplat.viewer.server import Viewer

        self.viewer = Viewer(self.scene_fn(), host=self.host, port=self.port, device=self.device,
                             render_thread=False)
        self.plot = self.viewer.server.gui.add_uplot(
            data=(np.zeros(1), np.zeros(1)), series=({"label": "step"}, {"label": "loss", "stroke": "red"}),
            title="training loss", aspect=1.6)
        print(f"clsplat train --view: watch the run at {self.viewer.url}", flush=True)

    def on_step(self, step: int, record: dict) -> None:
        """Called by the training loop after each step with its log record."""
        if self.viewer is None:
            self.start()
        if "loss" in record:
            self.steps.append(step)
            self.losses.append(float(record["loss"]))
        clients = self.viewer.clients()
        if not clients:
            self._seen = set()
            return
        if set(clients) - self._seen or step % self.every == 0:
            self._seen = set(clients)
            scene = self.scene_fn()
            self.viewer.set_gaussians(scene)
            if scene.depths:   # DrivingForward's and PGT's predicted depth, as it learns
                self.viewer.set_depths(scene)
            self.plot.data = (np.asarray(self.steps, np.float64), np.asarray(self.losses, np.float64))
            self.refreshes += 1
        self.viewer.render_due()

    def close(self) -> None:
        if self.viewer is not None:
            self.viewer.stop()


def train_watcher(args, scene_fn, device=None) -> TrainView | None:
    """The :class:`TrainView` of a ``clsplat train FAMILY`` run given :func:`~.cli.add_view_args`'
    arguments (None without ``--view``, and on ranks other than 0 under torchrun). A taken port is
    a ValueError now, before the run starts."""
    if not getattr(args, "view", False):
        return None
    from .train import distributed_info
    if distributed_info()[0] != 0:
        return None
    return TrainView(scene_fn, host=args.view_host, port=args.view_port, every=args.view_every, device=device)
