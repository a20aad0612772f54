"""Phase 3's evaluation (Appendix F): query and annotation files (`annotations`), the metrics
Acc / vIoU / tIoU of a query's activation (`query_metrics`, numpy only), `eval --queries` over
a run's field (`query_eval`) and relational question files (`relational_eval`). The activation
rules they score are Phase 3's own (`sync4d.phase3.activation`).
"""
