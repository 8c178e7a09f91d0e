from fleetmap.cli import main

raise SystemExit(main())
