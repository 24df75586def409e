"""Looking at results: traces compared (:mod:`.compare`), charts of runs (:mod:`.charts`), the
manipulator animated (:mod:`.animate`), models and FMUs documented (:mod:`.model_doc`) and the
design analysis presented (:mod:`.design`)."""
