from obliq_colmap.cli import main

raise SystemExit(main())
