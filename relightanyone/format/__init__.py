"""The normalized dataset format (version 1): schema, shards, reader, PyTorch dataset, validation.

Modules (import what you need; none of them is imported here, so the package stays light):

``schema``         Arrow schemas, typed rows (``ImageRow``, ``MeshRow``, ``LightRow``), manifest, quarantine
``codecs``         image (png16 / exr-half / raw-f16) and mask encoders and decoders
``shards``         ``ShardWriter``: atomic, deterministic, resumable writing from many workers
``reader``         ``NormalizedDataset``: memory-mapped rows by key in O(1)
``torch_dataset``  ``NormalizedTorchDataset``: the rows as the model reads them (a map-style torch Dataset)
``validate``       every check behind ``relightanyone validate``
``preview``        sRGB previews and ``render_contact_sheet`` (``relightanyone inspect``)
``examples``       small valid content for tests and benchmarks

See ``docs/format.md``.
"""
