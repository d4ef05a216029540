"""The classical NMPC on the true model: CasADi transcriptions (RK4 shooting `ocp`, Radau IIA collocation
`collocation`), its solvers (`nlpsol`, the real-time iteration `rti`) and the controller (`nmpc`,
`build_casadi_nmpc`), compiled to C and cached. Its only outside use is `controller.kind=casadi`."""
