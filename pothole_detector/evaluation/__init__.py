"""The evaluation: scoring the pipeline against datasets with ground truth (scores.py: the
paper's metrics, the validation scenes and drives as we are judged), the synthetic rig matrix
(rig_matrix.py) and our ray-cast stereo road generator with exact ground truth (synthetic.py).
The method knows nothing of it."""
