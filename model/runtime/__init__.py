"""The serving side of the model: numpy + onnxruntime + numba, never torch.

``loading`` (ONNX sessions and their typed metadata), ``frames`` (the visual encoder on one frame and the
per-session keypoint cache), ``pipeline`` (one session's state machine: features → fusion → FK → filter →
KPO → rotations), ``hands`` (the lost-controller policy), ``kernels`` (numba-compiled per-sample
arithmetic), ``kpo``, ``body`` (bone lengths), ``filters`` (One Euro). Import the submodules directly; this
package imports nothing so that the shared modules above it can use ``kernels`` without a cycle.
"""
