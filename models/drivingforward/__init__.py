"""clsplat.models.drivingforward: DrivingForward (Tian et al., AAAI 2025), feed-forward 3D
Gaussian splatting of surround-view driving scenes from any subset of cameras and frames,
trained self-supervised.

    presets     tiny / small / small-odometry / paper (DrivingForwardPreset, registered under "drivingforward")
    depth       the depth network (ResNet-18 encoder, scale-aware decoder, ground prior)
    pose        the pose network (one rig motion from all cameras fused in a bird's-eye grid)
    ground_motion  the rig motion fitted to the road's flow or images through the ground plane (a probe, issue 32)
    gaussian    the Gaussian network (per-pixel rotation, scale, opacity, colour)
    fusion      cross-view and cross-frame fusion of the per-view features
    model       DrivingForward (reconstruct -> GaussianSet; the training losses)
    losses      reprojection, smoothness, spatial and spatio-temporal terms
    data        frame triplets, colour jitter, ground-truth motion for the controls
    training    optimiser, warm-up, per-sample loss, the validation curve
    evaluation  held-out depth, pose and novel views with their image-blind controls
    view        the model in the viewer
    cli         ``clsplat train drivingforward`` / ``clsplat eval drivingforward``
"""
from . import presets as _presets  # noqa: F401  (registers the presets under "drivingforward")
