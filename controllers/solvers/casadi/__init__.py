"""The scenario problem as a CasADi NLP (:mod:`.nlp`) and the solvers built on CasADi's
plugins: IPOPT (:mod:`.ipopt`), ``sqpmethod`` + qpOASES (:mod:`.sqpmethod`) and csnlp's
``ScenarioBasedMpc`` (:mod:`.csnlp`). They are the references the fast solver is checked
against."""
