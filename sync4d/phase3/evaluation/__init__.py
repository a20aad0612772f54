"""Phase 3's evaluation (Appendix F): query and annotation files (`annotations`), the metrics
Acc / vIoU / tIoU (`metrics`, numpy only) and `eval --queries` over a run's field
(`evaluate`).
"""
