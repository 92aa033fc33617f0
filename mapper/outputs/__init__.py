"""What the mapper publishes besides query answers (module map: ARCHITECTURE.md).

* :mod:`mapper.outputs.layers`: layer messages (voxels, frontiers, rays) on
  ``<prefix>/mapper/layers/<layer>``, periodic put and get-on-demand.
* :mod:`mapper.outputs.rerun`: rerun recording of frames, the map and query answers.

A new output (e.g. ROS 2 topics) goes in its own module here, with a ``publish()`` /
``layers_published()``-style hook called from :meth:`mapper.outputs.layers.LayerPublisher.publish`
or the map worker, and is built in ``MapperService.__init__`` / ``start``.
"""
