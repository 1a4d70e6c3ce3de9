"""ajtwin.web — the browser dashboard (docs/howto/dashboard.md).

A FastAPI application (:func:`ajtwin.web.app.create_app`) serves three pages — the fleet,
one machine, and a what-if/advice form — from the machine registry, and pushes updates
to open pages over a websocket. Updates come from two sources:

* the registry itself (:class:`ajtwin.web.watcher.RegistryWatcher` notices prints that
  ``ajtwin ingest`` commits), and
* an in-process publisher (:class:`ajtwin.web.publisher.LivePublisher`) that a live
  engine calls once per sample.

Everything the pages need is read through :mod:`ajtwin.engine.views` (one adapter between
the registry's schema and the pages). Nothing here computes physics: forecasts and advice
call :mod:`ajtwin.apps.planning.forecast` and :mod:`ajtwin.apps.planning.advice`, the functions
behind
``ajtwin forecast`` and ``ajtwin advise``.

Start it with ``ajtwin dashboard [--store PATH] [--host 127.0.0.1 --port 8050]``.
"""
