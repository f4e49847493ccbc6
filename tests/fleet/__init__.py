# Fleet tests (rce_fleet is installed with the project from examples/fleet).
