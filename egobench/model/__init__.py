"""The model core: the image formation, the methods (one spec per paper row), prediction of a frame, rolling-shutter motion sampling, the learned lens shading and the optimiser glue."""
