"""One runner per pipeline stage: the computation of each stage in its own module.

A stage's code fingerprint is the import closure of its runner module alone
(:attr:`pipelines.stages.Stage.code`), so editing one runner reruns only its
stage (and the stages reading its outputs, when those change).
"""
