from onboard.behaviour import register


def half_written(:
