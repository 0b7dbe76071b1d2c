"""What the algorithms share: base class (:mod:`.twin_critic`), policies' parts (:mod:`.policies`), checks
(:mod:`.validation`) and saving (:mod:`.persistence`)."""
