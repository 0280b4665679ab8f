"""Issue 41: a cheaper keyframe network with the same maps.

* :mod:`.int8`  - why INT8 R2D2 gave NaN repeatability, and an INT8 faster2d2 with the heads kept in float;
* :mod:`.model` - the distilled student network (same ONNX contract as faster2d2);
* :mod:`.train` - distillation from the faster2d2 teacher, resumable, with ONNX export and a model card.

Run ``python -m twohr_lab.student.int8 --help`` and ``python -m twohr_lab.student.train --help``.
Nothing at run time imports this package.
"""
