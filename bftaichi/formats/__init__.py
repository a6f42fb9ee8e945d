"""Dataset formats: recorded RGB-D sequences on disk, read lazily as frames."""

from .readers import (
    FORMATS,
    POSE_CONVENTIONS,
    BFSDFDataset,
    CO3DDataset,
    Dataset,
    FolderDataset,
    RedwoodDataset,
    ReplicaDataset,
    ScanNetDataset,
    SevenScenesDataset,
    TUMDataset,
    detect_format,
    open_dataset,
    pytorch3d_to_opencv,
)
