"""The badf web viewer: a viser page showing live slices of the workers' distance fields.

    from badf.web_viewer import Viewer, ViewerSettings
    with Viewer(ViewerSettings(connect="tcp/127.0.0.1:7447", port=8080)) as viewer:
        print(viewer.url)

    with viewer_process(connect="tcp/127.0.0.1:7447") as url:   # the same, in a child process of its own
        ...

It talks to the workers over Zenoh only (badf.client) and never imports the worker. viser is imported
when a Viewer is made: `pip install 'badf[viewer]'`.
"""

from badf.web_viewer._process import viewer_process
from badf.web_viewer._viewer import Viewer, ViewerSettings, ViewerStatus

__all__ = ["Viewer", "ViewerSettings", "ViewerStatus", "viewer_process"]
