"""mtcw's benchmarks: measured speed and accuracy, never asserted in timed tests.

- :mod:`.grid`: scenes x echo losses x profiles x methods against the Cramér–Rao bound
  (``mtcw bench``; ``--quick`` in CI);
- :mod:`.report`: its CSV/JSON, figures and Markdown report;
- :mod:`.stream`: sustained frames/s and trigger-to-point latency of the services
  (``mtcw-bench-stream``);
- :mod:`.quasicw`: cycle slips and coarse-gate honesty of the quasi-CW bench over many frames
  (``mtcw-bench-quasicw``);
- :mod:`.honesty` and :mod:`.honesty_report`: the honesty map of issue 12 -- confident wrong
  answers, z-scores, missed and false targets over slices of the operating envelope
  (``mtcw bench --honesty`` / ``mtcw-bench-honesty``; ``--quick`` in CI).
"""
