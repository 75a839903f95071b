"""``cadestate annotate``: the four human tasks of the paper (Sec. 3.1-3.5) in a browser.

A local FastAPI app over a warehouse, one client of the label-file contract (as CVAT import is
another): every answer is validated exactly as ``cadestate labels ingest`` validates a file
(:func:`tasks.human.labels.validate_label`), written as a label file under ``<warehouse>/labels/<clip>/``
before the response returns, ingested (:func:`tasks.human.label_ingest.ingest_labels`), and the clip is
resumed in the background by one worker (:mod:`cadestate.webapp.resume`).

- :mod:`cadestate.webapp.queue`: the open tasks and items of each clip (what waits for people);
- :mod:`cadestate.webapp.answers`: an answer in, a label file out, ingested;
- :mod:`cadestate.webapp.resume`: the background resume of clips that got answers;
- :mod:`cadestate.webapp.claims`: the items held by the browsers that opened them (in the warehouse, ``_claims/``);
- :mod:`cadestate.webapp.overlays`: the posed model as image layers for the verification page;
- :mod:`cadestate.webapp.app`: the HTTP routes; ``static/``: the pages (plain HTML + JS modules;
  three.js from ``make web-vendor``, served locally).

Coordinates are the label format's (:mod:`schemas.labels`): boxes (ymin, xmin, ymax, xmax) and
image points (x, y) normalised to [0, 1], origin top-left; 3D points in the canonical CAD frame.
The pages convert to and from pixels of the displayed image only.
"""
