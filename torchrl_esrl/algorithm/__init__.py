"""The steps of Algorithm 1 (paper, Section 3): the TD3 phase, the ES phase, the overwrite rule
(Section 3.2), and the ES phase run in the background (``es.schedule=async``)."""
