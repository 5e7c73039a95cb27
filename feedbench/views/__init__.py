"""What a person sees of a result, as plain data: report sections (`sections`: plots,
tables, quality indicators) and live panels (`panels`: curves, images). Each experiment
family fills them from its analysis result; `feedbench.report` and `feedbench.gui` only
lay them out."""
