"""The fast SQP's quadratic programs: the QP with slacks in fixed row slots for qpOASES's hot
starts and the cold-started solvers (:mod:`.slot_qp`), the QP without slacks on DAQP
(:mod:`.hard_qp`), and the compiled interior point for the QP with slacks (:mod:`.elastic_ipm`)."""
