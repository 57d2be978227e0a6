"""Dataset readers and writers (KITTI, nuScenes, SynthCars) and instance datasets."""
