"""Progress of runs and scans: counts, verdicts and an ETA, as a bar or as lines."""

import io

from pipeline.orchestrate.progress import Bar, Lines, Progress


def test_a_scan_counts_suspects_and_their_verdicts_with_an_eta():
    stream = io.StringIO()
    progress = Lines(stream, every=3600.0)
    progress.start_scan(3)
    assert progress.eta() is None                          # nothing done: no estimate yet
    progress.suspect_done("no match")
    assert progress.eta() is not None and progress.eta() >= 0.0
    progress.suspect_done("match")
    progress.suspect_done("no match")                      # the last one is always said
    line = stream.getvalue().strip().splitlines()[-1]
    assert line.startswith("[pointmark] suspects 3/3 (1 match, 2 no match)") and line.endswith("ETA 0s")


def test_the_mode_picks_a_bar_on_a_terminal_and_lines_elsewhere():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert type(Progress.for_stream("auto", Tty())) is Bar
    assert type(Progress.for_stream("auto", io.StringIO())) is Lines
    assert type(Progress.for_stream("none", io.StringIO())) is Progress
