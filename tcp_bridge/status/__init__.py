"""The live status page (issue 25): ``tcp-bridge serve --http HOST:PORT``.

* :mod:`.rows`: pure; the replies of one axis's reads turned into one row (state,
  mode, decoded error bits);
* :mod:`.sampler`: reads every axis through the engine, as a client would, at a
  fixed period, and keeps the last minute;
* :mod:`.http`: a small read-only HTTP/1.1 server (``/``, ``/api/axes``,
  ``/api/history``, ``/api/stream``);
* :mod:`.page`: the page itself, one self-contained HTML text.

Nothing here imports asyncio at package level: :mod:`.rows` and :mod:`.page` stay pure.
"""
