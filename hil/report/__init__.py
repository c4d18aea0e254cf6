"""What a run tells its user: the verdict and its exit code (``verdict``), text and JSON reports
(``render``) and figures (``figures``)."""
