"""Running and reporting a scene: the pipeline's staging, report and outputs
(:mod:`.pipeline`), the memory guard (:mod:`.resources`), diagnostic plots (:mod:`.plots`)
and the 3-D preview (:mod:`.viz`)."""
