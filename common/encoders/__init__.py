"""Image-encoder model code shared by the edge (encoding frames) and the mapper (embedding
image queries in the map's feature space, on the base station).

* :mod:`common.encoders.radio` — RADIO v2.5 backbone (our own modules, published key names);
* :mod:`common.encoders.naclip` — NACLIP last-block attention;
* :mod:`common.encoders.heads` — the language (summary) head picked from a checkpoint;
* :mod:`common.encoders.naradio` — NARADIO = the three above, and its ``EncoderConfig``
  (:mod:`common.encoders.config`) and checkpoint lookup (:mod:`common.encoders.files`);
* :mod:`common.encoders.label_image` — the label encoder's image side (pixels classified by
  the synthetic world's class appearance, then class-name embeddings mixed).

torch is imported only by these modules; the query client never imports them (it sends the
image bytes). ``edge.encoders.radio`` etc. remain importable for the edge: they are the same
module objects.
"""
