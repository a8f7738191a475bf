"""The GPU kernels (Triton), each the fast path of a plain-torch reference elsewhere in the core:

* :mod:`.knn`: K nearest scaffold vertices within a radius (reference
  :func:`~neumesh_core.field.knn.knn_radius_reference`); ``knn_keys`` is the ``@triton.jit`` search the
  fused renderer calls per sample, :class:`~.knn.TritonKNNIndex` the field's neighbour index on a GPU.
* :mod:`.fused`: the fused renderer's host side: which path renders a call (:func:`~.fused.render_path`),
  the tables, launch options and launches (reference: the torch path of
  :func:`~neumesh_core.render.renderer.render_rays`).
* :mod:`.fused_kernel`: the fused renderer's kernel (march, neighbours, decoders, compositing), built
  from the decoders' ``@triton.jit`` parts in :mod:`.fused_decoders`.

Triton is optional (``pip install -e '.[gpu]'``): without it nothing here imports triton's kernels and
the torch references render.  Imported lazily by the field and the renderer; this package imports only
``errors`` and ``sampling`` of the core (the field imports it, never the other way).
"""
