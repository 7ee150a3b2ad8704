from cubecloud_cli.cli import main

if __name__ == "__main__":  # `python -m cubecloud_cli`; importing the module runs nothing
    main()
