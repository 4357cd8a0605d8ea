"""What every model family uses, and nothing model-specific.

    gaussians   GaussianSet (cat, index, rigid transform, .ply, render) and real-SH rotation
    geometry    pixel grids, unprojection, projection, inverse warping, SE(3)/SO(3) helpers
    data        --data specs (synthetic | pandaset:PATH | nuscenes:PATH) -> DrivingSequence windows
    presets     the frozen-dataclass preset base, registry and checkpoint check
    train       the training loop of every family: seeds, threads, JSONL log, loss PNG, checkpoints,
                resume, DDP; LoopHooks for staged families (parameter-group stages, densification)
    runfolder   a run's folder: one run at a time (lock), outputs staged and published as a group
    report      metrics.json: the one schema every family's evaluation writes
    cli         arguments every ``clsplat train|eval <family>`` command shares (models/README.md)
    view        checkpoints -> viewer scenes (each family's ``view`` module), ``train --view``
    backbones   ResNet-18 / VGG-16 with torchvision names, residual U-Net blocks, local weights
    losses      photometric (SSIM + L1), smoothness, Chamfer
    metrics     PSNR, SSIM, depth metrics, LPIPS (only with user-given weights)

Modules are imported on use (``from clsplat.models.common.gaussians import GaussianSet``), so
importing this package costs nothing.
"""
