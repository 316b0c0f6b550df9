"""The command lines' log set-up: the project's INFO lines shown, other libraries' INFO not."""
import logging

from forcecal.logs import configure_logging


def test_library_info_is_hidden_even_when_the_root_logger_is_raised_to_info(capsys):
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    try:
        configure_logging(logging.INFO, prefix="[rank 0] ")
        # what cffi's distutils verbosity does in the middle of an FFCx form build
        root.setLevel(logging.INFO)
        logging.info("running build_ext")
        logging.getLogger("ffcx").info("compiling form")
        logging.getLogger("reference_fe.run").info("test point 3 done")
        logging.getLogger("ffcx").warning("cache folder not writable")
        logging.getLogger("particle.integrator").debug("not at INFO")
        lines = capsys.readouterr().err.splitlines()
    finally:
        root.handlers[:], _ = saved[0], root.setLevel(saved[1])
    assert lines == ["[rank 0] INFO reference_fe.run: test point 3 done",
                     "[rank 0] WARNING ffcx: cache folder not writable"]
