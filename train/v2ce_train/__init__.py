"""Training of the V2CE Stage 1 network for v2ce (see ../README.md, "Training").

The generator is the V2CE 3D UNet at any width and depth (its full size has the official
parameter names and shapes); the losses are the five of the V2CE method with the reference
weights; data comes from ``v2ce dataset``; a trained generator is saved as a toolbox-format
state dict that ``v2ce model import`` turns into the ONNX model the learned tier runs.
"""
