"""One runner per pipeline stage: the computation of each stage in its own module.

A stage's code fingerprint holds its own runner and no other
(:data:`forcecal.provenance.STAGE_CODE`), so editing one runner reruns only its
stage (and the stages reading its outputs, when those change).
"""
