"""What people look at: Bode figures and the diagnosis report (:mod:`.plotting`,
:mod:`.report`), recorded sessions as Rerun files (:mod:`.rerun_export`) and the live
channels streamed from Zenoh to a viewer (:mod:`.live`)."""
