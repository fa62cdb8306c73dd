"""The reports: ``report.html`` of a run and its figures (:mod:`.page`), its words and numbers
(:mod:`.text`), and the element maps' report (:mod:`.elements`)."""
