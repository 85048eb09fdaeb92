"""The data model: what flows through hsiffc.

- :mod:`.frame` - :class:`~hsiffc.data.frame.Frame`, one mosaic frame or cube with its DQ plane,
  metadata and history;
- :mod:`.dq` - the data-quality bit flags and their table;
- :mod:`.mosaic` - the band layout of a snapshot mosaic;
- :mod:`.sweep` - :class:`~hsiffc.data.sweep.Sweep`, an exposure or light sweep of frames;
- :mod:`.bandstats` - statistics per band of a mosaic frame;
- :mod:`.dark` - master darks and their subtraction (DN in, DN out);
- :mod:`.params` - parameter declarations and checks shared by stages and functions;
- :mod:`.products` - the versioned product file (arrays + JSON manifest, no pickle).

This layer imports only :mod:`hsiffc.errors`, :mod:`hsiffc.files` and :mod:`hsiffc.kernels`.
"""
