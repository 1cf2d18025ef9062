"""The studies of the main job: the model report, the paper, the identification demo, `reproduce`."""
