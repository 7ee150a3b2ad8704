from cubecloud_cli.cli import main

if __name__ == "__main__":  # a spawned child (cubecloud_cli/side_by_side.py) imports this module too
    main()
